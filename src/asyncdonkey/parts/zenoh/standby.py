"""Which of two pilot servers answers the cars: a primary and its standby, decided from Zenoh liveliness tokens.

A fleet paired with ``zenoh-pair --fleet --server gpu1 --standby gpu2`` has two servers for the same cars:
every car connects to both and takes commands from either certificate. Exactly one of them should answer. The
servers tell each other what they do with Zenoh's own liveliness tokens (a token exists while the session
that declared it is connected; Zenoh withdraws it when that session closes, dies or misses its lease), on two
keys named after the primary:

* ``pilot-servers/<primary>/alive``: the primary declares it for as long as it runs;
* ``pilot-servers/<primary>/standby-answering``: the standby declares it while it answers;
* ``pilot-servers/<primary>/standby``: the standby declares it for as long as it runs (see *A server that was
  away*).

**The rule** (:class:`AnswerRule`, the same for both; each watches the other's token):

* the **standby answers while the primary's** ``alive`` **token is absent**;
* the **primary answers while the standby's** ``standby-answering`` **token is absent**.

Neither answers until it knows: a server starts *undecided*, watching its token (a liveliness subscriber, and
a liveliness query at once and every ``grace_s`` after, which puts right an event missed in a race), and
decides when the token appears, or after ``grace_s`` (1 s) without it; a primary also decides on its first
query's answer. A starting primary subscribes to the cars' frames first and declares its ``alive`` token only
once every car's frames reach it (or after ``ready_s``, 3 s): a car reconnects to a restarted server on its
own retry schedule (up to 2 s), and the standby must not hand back a car the primary cannot reach yet. A
standby declares its frame subscriptions only while it answers (the cars send it frames only then: an idle standby
costs no car any bandwidth); a server that stops answering first drops any answer still in its batch, then
(the standby) withdraws its subscriptions and its token. A primary answers only frames that reach it while it
answers.

**Takeover** (the primary dies). A killed process's sockets are closed by its OS, so the standby sees the
token go within a round trip; a machine that vanishes without closing them (power, cable) is noticed when its
lease runs out (the server configs of ``zenoh-pair --standby`` set 1 s). The standby then declares its
subscriptions, the cars' next frames reach it, and its answers go out; the car takes a new sender's numbering
from its second sample (:mod:`.sequence`), so a takeover costs about the detection, one frame period and one
model call. Measured in ``docs/scale-out.md``.

**Hand-back** (the primary returns). The primary's ``alive`` token reaches the standby, which stops answering
and withdraws ``standby-answering``; the primary, which has not answered yet (undecided, then waiting for that
token to go), answers the frames that reach it from then on. A frame is answered twice only if it reaches the
primary later than the standby's answer to it, the standby's withdrawal and that withdrawal's way to the
primary together (the standby stops answering before it withdraws its token); never seen in the measurements
(``docs/scale-out.md``), and if it happens the car keeps the first answer (``duplicates``).

**A split** (both alive, but they cannot see each other: a broken link between the servers while each still
reaches the cars). Each sees the other's token gone, so **both answer** every frame. The car takes the first
answer of a frame and counts the second as a ``duplicate`` (:class:`.ZenohSubscriber`: a command from another
sender whose origin is not newer than the held command's by more than ``same_frame_s``); either way a command's
age stays the age of its own frame. When the split heals, the standby sees ``alive`` and stops; the primary
sees ``standby-answering`` and stops too until the standby's token goes (a few ms): they converge to the
primary alone, without a livelock (the standby's state depends only on the primary being alive).

**A server that was away relearns** (a SIGSTOP, a suspended VM, a machine that hung with its sockets open). Its
peers dropped it when its lease ran out, and the other server may have taken over meanwhile; but what it last
knew says it answers, and its own session learns otherwise only once its peers reach it again. So a server
whose rule was not consulted for ``away_s`` (2 s; the server consults it every ``grace_s`` and at each answer)
is undecided again, as at its start: it answers nothing until the other's token appears (then it waits for it
to go), or a query sent after the other's running token (``standby``, ``alive``) reappeared finds the watched
one absent, or ``grace_s`` passes without either. A query sent earlier decides nothing: before the sessions are
back it is answered from what the session knew before the absence (seen: "absent" 5 ms after SIGCONT while the
standby still answered). The running token matters for a resumed primary: the standby sees ``alive`` come back
and withdraws ``standby-answering``, often before the primary's session hears of that token at all, so no event
of the watched token would ever tell the primary; but the ``standby`` token reappears once the sessions have
reconnected, and a query from then on is answered by the standby's own session. Measured in
``docs/scale-out.md``: a resumed primary answers nothing beside the standby, where it otherwise answered the
cars' next frames with it for up to 0.1 s.

:class:`AnswerRule` is the decision alone (tested with fake token events on a controlled clock);
:class:`RoleWatch` is the Zenoh side (tokens, the liveliness subscriber) feeding it.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ...errors import AsyncdonkeyError

__all__ = [
    "AWAY_S",
    "GRACE_S",
    "READY_S",
    "AnswerRule",
    "RoleWatch",
    "ServerRole",
    "StandbyConfigError",
    "alive_key",
    "answering_key",
    "standby_key",
]

logger = logging.getLogger(__name__)

#: how long a server watches before it decides, when the other's token has not appeared
GRACE_S = 1.0
#: the longest a starting primary waits for every car's frames before it declares its token
READY_S = 3.0
#: a server whose rule was not consulted for this long was away (frozen, suspended) and relearns its pair
AWAY_S = 2.0
#: the subjects' ids in the server configs of ``zenoh-pair --fleet --standby`` (how a server learns its role)
PRIMARY_SUBJECT = "pair-primary"
STANDBY_SUBJECT = "pair-standby"


class StandbyConfigError(AsyncdonkeyError, ValueError):
    """A primary/standby pair is configured so that it could not work (the message says what is missing)."""


def alive_key(primary: str) -> str:
    """The primary's liveliness token: declared for as long as it runs."""
    return f"pilot-servers/{primary}/alive"


def answering_key(primary: str) -> str:
    """The standby's liveliness token: declared while it answers the cars."""
    return f"pilot-servers/{primary}/standby-answering"


def standby_key(primary: str) -> str:
    """The standby's presence token: declared for as long as it runs."""
    return f"pilot-servers/{primary}/standby"


def pair_keys(primary: str) -> str:
    """The key expression covering the tokens of a pair (what the servers' access rules allow between them, and
    what each server's liveliness subscriber watches)."""
    return f"pilot-servers/{primary}/**"


@dataclass(frozen=True)
class ServerRole:
    """A server's place in a pair: ``name`` its own name; ``primary`` the primary it stands by for (a standby),
    or ``None`` (a primary, whose standby is ``standby``)."""

    name: str
    primary: str | None = None
    standby: str | None = None

    def __post_init__(self) -> None:
        if self.primary is not None and self.primary == self.name:
            raise StandbyConfigError(f"pilot server {self.name!r} cannot be the standby of itself")
        if self.primary is not None and self.standby is not None:
            raise StandbyConfigError(f"pilot server {self.name!r} is either a primary or a standby, not both")

    @property
    def is_standby(self) -> bool:
        return self.primary is not None

    @property
    def pair(self) -> str:
        """The primary's name: the pair's keys are named after it."""
        return self.primary if self.primary is not None else self.name

    @property
    def watched(self) -> str:
        """The other server's token this one watches: it answers while that token is absent."""
        return alive_key(self.pair) if self.is_standby else answering_key(self.pair)

    @property
    def other_running(self) -> str:
        """The other server's token that exists while it runs: its appearance says the sessions are back."""
        return alive_key(self.pair) if self.is_standby else standby_key(self.pair)

    def describe(self) -> str:
        if self.is_standby:
            return f"standby of {self.primary!r}: answers while {self.primary!r} is not alive"
        return f"primary{f' (standby {self.standby!r})' if self.standby else ''}: answers unless its standby does"


def role_from_config(cfg: Any, name: str | None = None) -> ServerRole | None:
    """The role written into a server config by ``zenoh-pair --fleet --standby`` (the subjects ``pair-primary``
    or ``pair-standby`` of its access rules), or ``None`` for a server without a pair. ``name``: this server's
    name (default: the common name of its certificate)."""
    from .certs import config_value

    subjects = config_value(cfg, "access_control/subjects") or []
    by_id = {s.get("id"): s.get("cert_common_names") or [] for s in subjects if isinstance(s, dict)}
    primary = (by_id.get(PRIMARY_SUBJECT) or [None])[0]
    standby = (by_id.get(STANDBY_SUBJECT) or [None])[0]
    if primary is None and standby is None:
        return None
    own = name or _own_name(cfg)
    if own is None:
        raise StandbyConfigError("pilot server: its config pairs it with another server, but names no certificate")
    return ServerRole(own, primary=primary, standby=standby if primary is None else None)


def _own_name(cfg: Any) -> str | None:
    """The common name of the certificate a config names (``transport/link/tls/connect_certificate``)."""
    from .certs import config_value

    path = config_value(cfg, "transport/link/tls/connect_certificate")
    if not isinstance(path, str):
        return None
    try:
        from cryptography import x509
        from cryptography.x509.oid import NameOID

        with open(path, "rb") as f:
            cert = x509.load_pem_x509_certificate(f.read())
        names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        return str(names[0].value) if names else None
    except Exception:  # unreadable: the session will say so when it opens
        return None


class AnswerRule:
    """Whether a server answers now (module docstring): while the watched token is absent, once decided.

    Events come from :class:`RoleWatch` (or a test): :meth:`token` for each appearance and withdrawal of the
    watched token. A server is undecided for ``grace_s`` after ``start`` unless the token appeared: it answers
    from then on while the token is absent. A call (any of them) more than ``away_s`` after the previous one makes
    it undecided again from that moment (the server was away: module docstring): until it decides again a
    query's absence decides only once :meth:`running` has said the other's running token reappeared (the caller
    sends a query then). A query's answer is stale when a token event came while it was out, or, while relearning,
    the running token's: the caller takes :meth:`asking` when it sends one and hands it back with the answer.
    ``switches`` records every change of the answer, ``(time, answering)``; ``away`` every return from an
    absence, ``(time, seconds away)``.
    """

    def __init__(self, start: float, grace_s: float = GRACE_S, away_s: float = math.inf) -> None:
        if not (math.isfinite(grace_s) and grace_s >= 0):
            raise ValueError(f"AnswerRule: grace_s must be a number of seconds >= 0, got {grace_s!r}")
        if not (away_s > grace_s):
            raise ValueError(f"AnswerRule: away_s must be longer than grace_s ({grace_s!r} s), got {away_s!r}")
        self.start = float(start)
        self.grace_s = float(grace_s)
        self.away_s = float(away_s)
        #: relearning, the other's running token has reappeared: a query from now on is answered by it
        self.reached = False
        self.present = False
        self.decided = False
        self.relearning = False
        self.last = False
        self.consulted = self.start
        #: events that make an earlier query's answer stale (see :meth:`asking`)
        self.heard = 0
        self.switches: list[tuple[float, bool]] = []
        self.away: list[tuple[float, float]] = []

    def token(self, present: bool, now: float) -> bool:
        """The watched token appeared (``True``) or went (``False``); returns whether to answer now. Its going
        decides only a server relearning once the other was :attr:`reached` (before, it may be the closing of
        the session that was dropped during the absence, not the other's doing)."""
        self._returned(now)
        self.heard += 1
        self.present = bool(present)
        if present or (self.relearning and self.reached):
            self._decide()  # seen: the other's state is known from now on
        return self.answering(now)

    def asking(self) -> int:
        """A query is being sent: what to hand back to :meth:`queried` with its answer."""
        return self.heard

    def queried(self, present: bool, now: float, decides_absence: bool, asked: int | None = None) -> bool:
        """The answer of a liveliness query: the token is there or not. Presence decides; absence decides only
        when ``decides_absence`` (a primary, which queries once the cars reach it, long after it dialled its
        standby; a standby's session may not have reached its primary yet at start, so its grace decides), and,
        while the server relearns after an absence, only for a query sent once the other was :attr:`reached`.
        ``asked``: :meth:`asking` when the query was sent; an answer overtaken by an event since is ignored (the
        event is newer). Only an event about the watched token, or the running token's while relearning (a query
        sent before it was answered from what the session knew before the absence), overtakes it: the other's
        running token seen at a primary's start says nothing about what the other does."""
        if asked is not None and asked != self.heard:
            return self.answering(now)
        self._returned(now)
        self.present = bool(present)
        if present or (decides_absence and (self.reached or not self.relearning)):
            self._decide()
        return self.answering(now)

    def running(self, present: bool, now: float) -> bool:
        """The other server's running token appeared (``True``) or went: while relearning, its appearance says
        the sessions are back (:attr:`reached`), so that a query sent from then on decides."""
        self._returned(now)
        if self.relearning:
            self.heard += 1
            self.reached = bool(present)
        return self.answering(now)

    def answering(self, now: float) -> bool:
        """Whether to answer at ``now`` (records a switch when the answer changes)."""
        self._returned(now)
        if not self.decided and now - self.start >= self.grace_s:
            self._decide()
        answer = self.decided and not self.present
        if answer != self.last:
            self.last = answer
            self.switches.append((now, answer))
        return answer

    def _decide(self) -> None:
        self.decided = True
        self.relearning = False
        self.reached = False

    def _returned(self, now: float) -> None:
        """Undecided again, from ``now``, when the previous call was more than ``away_s`` ago."""
        gap = now - self.consulted
        self.consulted = max(self.consulted, now)
        if gap > self.away_s:
            self.away.append((now, gap))
            self.start = now
            self.decided = False
            self.relearning = True
            self.reached = False


class RoleWatch:
    """The Zenoh side of a pair (module docstring): this server's own token, and the other's watched.

    ``on_event(present)`` is called on Zenoh's thread for each appearance (``True``) or withdrawal of the
    watched token, ``on_running(present)`` for the other's running token when it is another key (the
    primary's watch); hand them to the event loop. :meth:`answering` declares or withdraws the standby's
    ``standby-answering`` token (a primary declares nothing more). Its own running token (``alive`` for the
    primary, ``standby`` for the standby) is declared for as long as the watch is open.
    """

    def __init__(
        self,
        session: Any,
        role: ServerRole,
        on_event: Callable[[bool], None],
        on_running: Callable[[bool], None] | None = None,
    ) -> None:
        import zenoh

        self.session = session
        self.role = role
        self._lock = threading.Lock()
        self._token: Any = None
        self._answering: Any = None
        self._kind_put = zenoh.SampleKind.PUT
        self._on_event = on_event
        self._on_running = on_running
        self._watched, self._running = role.watched, role.other_running
        liveliness = session.liveliness()
        self._token = liveliness.declare_token(standby_key(role.pair) if role.is_standby else alive_key(role.pair))
        self._sub = liveliness.declare_subscriber(pair_keys(role.pair), self._on_sample, history=True)

    def _on_sample(self, sample: Any) -> None:
        key, present = str(sample.key_expr), sample.kind == self._kind_put
        if key == self._watched:
            self._on_event(present)
        elif key == self._running and self._on_running is not None:
            self._on_running(present)

    def query(self, on_result: Callable[[bool], None]) -> None:
        """Ask the network whether the watched token is there now; ``on_result(present)`` on Zenoh's thread when
        the query completes. Events can be missed in a race (a token withdrawn while a subscription's history
        is on its way): a periodic query puts the rule right."""
        import zenoh

        replies: list[Any] = []
        try:
            self.session.liveliness().get(
                self.role.watched,
                handler=zenoh.handlers.Callback(
                    replies.append, lambda: on_result(any(r.ok is not None for r in replies))
                ),
            )
        except Exception:  # the session is closing
            pass

    def answering(self, answering: bool) -> None:
        """Declare (``True``) or withdraw this standby's ``standby-answering`` token; a primary: nothing."""
        if not self.role.is_standby:
            return
        with self._lock:
            if answering and self._answering is None:
                self._answering = self.session.liveliness().declare_token(answering_key(self.role.pair))
            elif not answering and self._answering is not None:
                token, self._answering = self._answering, None
                _undeclare(token)

    def close(self) -> None:
        for decl in (self._sub, self._answering, self._token):
            if decl is not None:
                _undeclare(decl)
        self._answering = self._token = None


def _undeclare(decl: Any) -> None:
    try:
        decl.undeclare()
    except Exception:  # the session is closing
        pass


def role_for(
    cfg: Any, *, name: str | None = None, standby_of: str | None = None, standby: str | None = None
) -> ServerRole | None:
    """The role a server runs in (``asyncdonkey pilot-server``): ``standby_of`` (a standby of that primary) or
    ``standby`` (a primary with that standby) when given, else what its config says (:func:`role_from_config`),
    else ``None`` (alone). ``name``: this server's name (default: its certificate's common name).

    Refused (:class:`StandbyConfigError`, one line): both given; a pair without a name; and a standby whose
    session dials nobody, since it could never see its primary alive and would answer beside it.
    """
    from .certs import config_value

    if standby_of and standby:
        raise StandbyConfigError("a pilot server is the standby of another (--standby-of) or has one (--standby)")
    if standby_of or standby:
        own = name or _own_name(cfg)
        if own is None:
            raise StandbyConfigError(
                "a pilot server of a pair needs a name, the other server watches its token by it: give --name"
            )
        role: ServerRole | None = ServerRole(own, primary=standby_of or None, standby=standby or None)
    else:
        role = role_from_config(cfg, name)
    if role is not None and role.is_standby:
        endpoints = config_value(cfg, "connect/endpoints") or []
        if isinstance(endpoints, dict):
            endpoints = endpoints.get("router", []) + endpoints.get("peer", [])
        if not endpoints:
            raise StandbyConfigError(
                f"standby {role.name!r} of {role.primary!r} dials no other session, so it could never see"
                f" {role.primary!r} alive and would answer beside it: give the primary's endpoint (--connect, or the"
                " standby config of `asyncdonkey zenoh-pair --fleet --standby`)"
            )
    return role
