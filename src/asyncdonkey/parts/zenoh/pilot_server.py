"""A fleet on one pilot server: every car's frames in, one batched model call, each car its own command back.

::

    server = PilotServer(BatchPilot("pilot.onnx"), ["car1", "car2", "car3"], config="pair/server/server.json5")
    await server.serve()                      # until server.stop(); `asyncdonkey pilot-server` wraps this

**Channel contracts as the remote pilot's.** For each car the server takes ``cam/image_array`` from
``cars/<car>`` with a :class:`.ZenohSubscriber` (the frame checked against the channel's contract, its origin
carried across the network, the round trip measured) and answers with a :class:`.ZenohPublisher` of
``pilot/angle, pilot/throttle`` as one sample on ``cars/<car>/pilot/command`` (``group=PILOT_COMMAND``), aged
by *that car's frame*: the car's ``pilot/throttle@age`` is its own camera-to-command time, exactly as with
``examples/remote_pilot.py``. A car needs no change to move from its own remote pilot to a server.

**Batching** (:class:`.FrameBatcher`, :class:`.BatchLoop`): the first frame to arrive opens a window of
``window_s`` (5 ms by default); the newest frame of each car that arrived by then goes into one model call
(:class:`.BatchPilot`), in arrival order; a frame older than ``max_age_s`` (the cars' failsafe window) is not
inferred (``too_old``). The call runs in the server's own worker thread, so Zenoh's callbacks and the event
loop keep taking frames meanwhile; those form the next batch as soon as the call returns.

**What the server never does**: keep a car moving. It has no failsafe of its own and needs none: a car whose
server is slow, overloaded or gone stops by its own stale-command stop (``PWMThrottle``'s failsafe or
:class:`~asyncdonkey.parts.failsafe.StaleCommandStop`), unchanged, because the commands it gets stop being
fresh. Who may command which car is the job of the fleet configs of ``asyncdonkey zenoh-pair --fleet``
(:mod:`.pairing`).

Counters: :meth:`counters` per car (``frames``, ``replaced``, ``too_old``, ``batched``, ``answered``, ``late``,
``refused``, ``wrong_frames``); :meth:`figures` the server's totals, each named as what it counts (frames
received, inferred, answered; batches and frames per batch; model calls, counted by the model; the time per
batch and per call: :class:`.ServerFigures`).
"""

from __future__ import annotations

import asyncio
import collections
import inspect
import logging
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...clock import get_clock
from ...extras import require
from ...ratelimit import LogThrottle
from .batcher import BatchLoop, Frame, FrameBatcher
from .certs import log_certificate_problems
from .link import ZenohConfigError, ZenohLink, exposure, link_config
from .pairing import PILOT_COMMAND
from .parts import ZenohPublisher, ZenohSubscriber
from .server_figures import ServerFigures
from .standby import AWAY_S, GRACE_S, READY_S, AnswerRule, RoleWatch, ServerRole, role_from_config

__all__ = ["PilotServer"]

logger = logging.getLogger(__name__)

CAMERA = "cam/image_array"
COMMAND = ("pilot/angle", "pilot/throttle")


class _Car:
    """One car's channels on the server: its frames in, its commands out, on the shared session.

    The commands' publisher lives as long as the server (one numbering for the car's sequence rules across
    every takeover); the frames' subscriber only while the server answers (:meth:`listen`, :meth:`quiet`), so
    a car sends its frames to the answering server only.
    """

    def __init__(self, name: str, session: Any, prefix: str, ping_every_s: float, silent_after_s: float) -> None:
        self.name = name
        self.link = ZenohLink(prefix, session=session).acquire()  # held: the frames' subscriber comes and goes
        self.ping_every_s = ping_every_s
        self.silent_after_s = silent_after_s
        self.frames: ZenohSubscriber | None = None
        self._unsubscribe: Callable[[], None] | None = None
        self._pings: asyncio.Future[None] | None = None
        self.refused_before = 0  # frames refused by the subscribers of earlier turns
        self.commands = ZenohPublisher(self.link, list(COMMAND), group=PILOT_COMMAND)
        self.answered = 0
        self.late = 0  # commands sent when their frame was already older than the failsafe window
        self.wrong_frames = 0

    def listen(self, push: Callable[[Any, float], None]) -> None:
        """Subscribe to the car's frames (the car sends them here from now on) and measure its round trip."""
        if self.frames is not None:
            return
        self.frames = ZenohSubscriber(
            self.link, [CAMERA], ping_every_s=self.ping_every_s, silent_after_s=self.silent_after_s
        )
        self._unsubscribe = self.frames.subscribe(push)
        self._pings = asyncio.ensure_future(self.frames.update())

    def quiet(self) -> None:
        """Withdraw the frames' subscription (the car stops sending frames here)."""
        frames, self.frames = self.frames, None
        if frames is None:
            return
        if self._pings is not None:
            self._pings.cancel()
        if self._unsubscribe is not None:
            self._unsubscribe()
        self.refused_before += frames.counters()["refused"]
        try:
            frames.shutdown()
        except Exception:  # pragma: no cover - closing a session that is going away
            pass

    def refused(self) -> int:
        """Frames the channel contract refused, over every turn."""
        return self.refused_before + (self.frames.counters()["refused"] if self.frames is not None else 0)

    def close(self) -> None:
        self.quiet()
        try:
            self.commands.shutdown()
        except Exception:  # pragma: no cover - closing a session that is going away
            pass
        self.link.release()


class PilotServer:
    """Serve a fleet's pilot commands from one model (see the module docstring).

    Args:
        model: a :class:`.BatchPilot`, or any ``infer(frames) -> [(angle, throttle) | None, ...]`` callable
            (sync: run in the server's worker thread; async: awaited on the loop).
        cars: the car names; each car's keys are ``prefix.format(car=name)``.
        config: the Zenoh config (a ``zenoh.Config``, a file such as ``server.json5`` from ``zenoh-pair
            --fleet``, or ``None``: loopback only); or give ``session``.
        session: an open Zenoh session to use (not closed by the server).
        window_s: how long the first frame of a batch waits for the other cars' frames.
        max_age_s: the cars' failsafe window: a frame older than this when its batch is taken is not inferred.
        max_batch: the most frames per model call.
        prefix: the key prefix of a car, with ``{car}`` for its name.
        ping_every_s: round-trip measurement per car (keeps the frames' ages true; 0: never).
        silent_after_s: when a car's frames have not come for this long, log once why, as far as the server can
            tell (:meth:`.ZenohSubscriber.silence_report`); ``0``: never.
        insecure: open the session even though others could publish to it (see below). For an isolated bench.
        role: this server's place in a primary/standby pair (:class:`.standby.ServerRole`): it then answers only
            while the other does not (:mod:`.standby`). Default: the role its config says
            (``zenoh-pair --fleet --standby``), or none (it answers from the start, alone).
        grace_s: a server of a pair watches this long for the other's token before it decides to answer.
        ready_s: a primary of a pair declares its token (so its standby hands back) once every car's frames
            reach it, or this long after it starts.
        away_s: a server of a pair whose loop did not consult its rule for this long (frozen, suspended)
            relearns what the other does before it answers again (:mod:`.standby`).

    **Frames are commands.** Whoever can publish ``cars/car1/cam/image_array`` to the server chooses the frames
    car1's command is computed from, and so steers car1. The server therefore refuses
    (:class:`.ZenohConfigError`, naming why) to open a session that others can publish to
    (:func:`.link.exposure`: plain TCP beyond loopback, multicast scouting, mutual TLS without access rules)
    unless ``insecure=True``; the configs of ``zenoh-pair --fleet`` let each car publish its own keys only.

    A frame that is not the model's ``image_shape`` uint8 RGB (``model.pilot.image_shape`` for a
    :class:`.BatchPilot`) is dropped before it reaches a batch (counted in ``wrong_frames``, logged once per
    5 s per car): one car with another camera must not cost the others their batch.
    """

    def __init__(
        self,
        model: Any,
        cars: Sequence[str],
        *,
        config: Any = None,
        session: Any = None,
        window_s: float = 0.005,
        max_age_s: float = 0.25,
        max_batch: int = 32,
        prefix: str = "cars/{car}",
        ping_every_s: float = 0.5,
        insecure: bool = False,
        silent_after_s: float = 5.0,
        role: ServerRole | None = None,
        grace_s: float = GRACE_S,
        ready_s: float = READY_S,
        away_s: float = AWAY_S,
    ) -> None:
        names = list(dict.fromkeys(cars))
        if not names or isinstance(cars, str):
            raise ValueError(f"PilotServer: give the car names as a list, got {cars!r}")
        if "{car}" not in prefix:
            raise ValueError(f"PilotServer: prefix must contain '{{car}}', got {prefix!r}")
        self.model = model
        self.batcher = FrameBatcher(window_s=window_s, max_age_s=max_age_s, max_batch=max_batch)
        self.loop = BatchLoop(self.batcher, getattr(model, "infer", model), self._answer)
        self.image_shape: tuple[int, ...] | None = getattr(getattr(model, "pilot", None), "image_shape", None)
        self._log = LogThrottle(5.0)
        self._owned = session is None
        #: the config the server opened its session with (``None`` for a session given to it)
        self.config: Any = None
        if session is None:
            self.config = link_config(config)
            session = self._open(self.config, insecure)
        self.session = session
        #: this server's place in a primary/standby pair (:mod:`.standby`; ``None``: it answers alone)
        self.role = role if role is not None else (role_from_config(self.config) if self.config is not None else None)
        self.grace_s = grace_s
        self.ready_s = ready_s
        self.away_s = away_s
        self._returns = 0  # returns from an absence logged (len(rule.away))
        self._seen: set[str] = set()  # cars whose frames reached this server (a primary waits for them)
        #: whether it answers the cars now; :attr:`rule` says when that changed (a pair only)
        self.answering = False
        self.rule: AnswerRule | None = None
        #: commands computed but not sent because the server had stopped answering meanwhile
        self.withheld = 0
        self._watch: RoleWatch | None = None
        self._event_loop: asyncio.AbstractEventLoop | None = None
        self.cars: dict[str, _Car] = {}
        try:
            for name in names:
                car = self.cars[name] = _Car(name, session, prefix.format(car=name), ping_every_s, silent_after_s)
                car.link.config = self.config  # what a silence report checks the certificates of
        except Exception:
            self.close()
            raise

    @staticmethod
    def _open(config: Any, insecure: bool) -> Any:
        zenoh = require("zenoh", "zenoh", "the pilot server")
        why = exposure(config)
        if why and not insecure:
            raise ZenohConfigError(
                f"PilotServer: refusing to serve on a session others can publish to: it {'; '.join(why)}, and"
                " whoever sends a car's frames steers that car. Use the server config of `asyncdonkey zenoh-pair"
                " --fleet` (mutual TLS and access rules), or listen on 127.0.0.1 only; on an isolated bench,"
                " insecure=True (--insecure)."
            )
        if why:
            logger.warning("pilot server: anyone who can reach this session can steer the cars (it %s)", "; ".join(why))
        log_certificate_problems(config, "pilot server")
        try:
            return zenoh.open(config)
        except Exception as exc:
            raise ZenohConfigError(f"PilotServer: cannot open a Zenoh session: {exc}") from None

    # -- frames in (Zenoh's threads, handed to the loop) --------------------------------------------------
    def _offer(self, car: str, image: Any, origin: float) -> None:
        if self.role is not None:
            self._seen.add(car)
            if not self.answering:  # a primary hears frames before it answers: none of them is answered
                if self._watch is None and len(self._seen) == len(self.cars):
                    self._watch_pair()
                return
        shape = self.image_shape
        if shape is not None and (getattr(image, "shape", None) != shape or getattr(image, "dtype", None) != np.uint8):
            entry = self.cars[car]
            entry.wrong_frames += 1
            if self._log.allow(car, get_clock().now()):
                got = f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray) else type(image).__name__
                logger.warning(
                    "pilot server: car %r sent a frame of %s; the model takes %s uint8 RGB: dropped (%d so far)",
                    car,
                    got,
                    shape,
                    entry.wrong_frames,
                )
            return
        self.loop.offer(car, image, origin)

    def _push(self, car: str, loop: asyncio.AbstractEventLoop) -> Callable[[Any, float], None]:
        offer = self._offer

        def push(image: Any, origin: float) -> None:
            try:
                loop.call_soon_threadsafe(offer, car, image, origin)
            except RuntimeError:  # the event loop is closed: the server is going away
                pass

        return push

    def _answer(self, frame: Frame, command: tuple[float, float], now: float) -> None:
        """Send a car its command, aged by the frame it answers (its capture, carried across the network); not
        once this server has stopped answering (the other server of its pair answers from then on)."""
        car = self.cars[frame.car]
        if self.answering and self.rule is not None:
            self._judge()  # a server back from an absence (its loop frozen) must not answer on what it knew
        if not self.answering:
            self.withheld += 1
            return
        age = max(0.0, now - frame.origin)
        if self.role is not None and car.commands.sent == 0:
            # a car takes a new sender from its second sample (.sequence): a server taking over sends its first
            # command twice (numbers 1 and 2, the same frame's), so the car takes it now, not a frame later
            car.commands.run(command[0], command[1], age, age)
        car.commands.run(command[0], command[1], age, age)
        car.answered += 1
        if age > self.batcher.max_age_s:
            car.late += 1

    # -- serving -------------------------------------------------------------------------------------------
    async def serve(self) -> None:
        """Take frames, infer them in batches and answer each car, until :meth:`stop`. A server of a pair
        answers only while its rule says so (:mod:`.standby`)."""
        loop = self._event_loop = asyncio.get_running_loop()
        clock = get_clock()
        for car in self.cars.values():
            car.link.now = clock.now
        if self.role is None:
            self._set_answering(True)
        else:
            await self._warm_up()  # before the other server learns of this one: its first answer is not late
            logger.info("pilot server %r: %s", self.role.name, self.role.describe())
            if self.role.is_standby:
                self._watch_pair()
            else:  # a primary: the cars' frames first (they reconnect at their own pace), then its token
                for car in self.cars.values():
                    car.listen(self._push(car.name, loop))
                loop.call_later(self.ready_s, self._watch_pair)
        try:
            await self.loop.serve()
        finally:
            self._set_answering(False)
            for car in self.cars.values():
                car.quiet()
            if self._watch is not None:
                self._watch.close()
                self._watch = None

    def _watch_pair(self) -> None:
        """Declare this server's token and watch the other's (:mod:`.standby`); a primary does so once every
        car's frames reach it, or ``ready_s`` after its start, so that the standby hands back only cars it can
        answer (a car whose link to it broke reconnects on its own schedule, up to 2 s)."""
        if self._watch is not None or self.role is None or self._event_loop is None:
            return
        self.rule = AnswerRule(get_clock().now(), self.grace_s, self.away_s)
        self._watch = RoleWatch(self.session, self.role, self._token_seen, self._running_seen)
        self._event_loop.call_later(self.grace_s + 1e-3, self._judge)
        self._query()

    def _query(self) -> None:
        """Ask whether the other's token is there (at once, then every ``grace_s``): a primary decides on the
        first answer; every answer puts right an event missed in a race (:meth:`.RoleWatch.query`)."""
        loop, watch = self._event_loop, self._watch
        if loop is None or watch is None:
            return
        self._judge()  # the loop's own pulse: a late one means it was away (:class:`.AnswerRule`)
        self._ask()
        loop.call_later(max(self.grace_s, 0.1), self._query)

    def _ask(self) -> None:
        """One liveliness query; its answer is applied unless a token event came while it was out."""
        watch, rule = self._watch, self.rule
        if watch is None or rule is None:
            return
        asked = rule.asking()
        watch.query(lambda present: self._to_loop(self._queried, present, asked))

    def _queried(self, present: bool, asked: int) -> None:
        """A query's answer (on the loop); the rule ignores one an event overtook (:meth:`.AnswerRule.queried`)."""
        rule, role = self.rule, self.role
        if rule is None or role is None or self._watch is None:
            return
        self._apply(rule.queried(present, get_clock().now(), decides_absence=not role.is_standby, asked=asked))

    async def _warm_up(self) -> None:
        """One model call on a blank frame, off the loop: a runtime's first call allocates and can take many
        times a normal one, which a server taking over (or taking back) the cars would add to their gap. A model
        with ``warm_up()`` (:meth:`.BatchPilot.warm_up`) makes it without counting it among its cars' calls."""
        shape = self.image_shape
        infer = getattr(self.model, "infer", self.model)
        warm_up = getattr(self.model, "warm_up", None)
        if shape is None:
            return
        try:
            if callable(warm_up):
                await asyncio.get_running_loop().run_in_executor(None, warm_up)
            elif inspect.iscoroutinefunction(infer):
                await infer([np.zeros(shape, np.uint8)])
            else:
                await asyncio.get_running_loop().run_in_executor(None, infer, [np.zeros(shape, np.uint8)])
        except Exception as exc:  # the batches will say so again
            logger.warning("pilot server: the model failed on a blank frame at start (%s)", exc)

    def _to_loop(self, fn: Callable[..., None], *args: Any) -> None:
        """``fn(*args)`` on the server's event loop, from one of Zenoh's threads; nothing once the loop is gone."""
        loop = self._event_loop
        if loop is None:
            return
        try:
            loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # the event loop is closed: the server is going away
            pass

    def _token_seen(self, present: bool) -> None:
        """The other server's token appeared or went (Zenoh's thread): judged on the loop."""
        self._to_loop(self._judge, present)

    def _running_seen(self, present: bool) -> None:
        """The other server's running token appeared or went (Zenoh's thread): on the loop, where a relearning
        server asks at once what the other does (:class:`.AnswerRule`)."""
        self._to_loop(self._ran, present)

    def _ran(self, present: bool) -> None:
        rule = self.rule
        if rule is None or self._watch is None:
            return
        self._apply(rule.running(present, get_clock().now()))
        if rule.reached:
            self._ask()

    def _judge(self, present: bool | None = None) -> None:
        """Apply the pair's rule now (on the loop), after a token event or when the grace ends."""
        rule = self.rule
        if rule is None or self._watch is None:
            return
        now = get_clock().now()
        self._apply(rule.answering(now) if present is None else rule.token(present, now))

    def _apply(self, answer: bool) -> None:
        """Start or stop answering when the rule's answer changed (logged); after an absence, decide again once
        the grace has passed (:class:`.AnswerRule`)."""
        role, rule, loop = self.role, self.rule, self._event_loop
        assert role is not None and rule is not None
        if len(rule.away) > self._returns:
            self._returns = len(rule.away)
            logger.warning(
                "pilot server %r: its loop was away %.1f s (frozen or suspended): it answers again once it knows"
                " what the other server of its pair does",
                role.name,
                rule.away[-1][1],
            )
            if loop is not None:
                loop.call_later(self.grace_s + 1e-3, self._judge)
        if answer != self.answering:
            other = f"{role.primary!r} is not alive" if role.is_standby else "its standby does not answer"
            stopped = "until it knows" if rule.relearning else "(the other server of its pair does)"
            logger.warning(
                "pilot server %r: %s",
                role.name,
                f"answering the cars ({other})" if answer else f"stopped answering {stopped}",
            )
            self._set_answering(answer)

    def _set_answering(self, answering: bool) -> None:
        """Start answering: the standby's token, then the frames' subscriptions. Stop: no answer from now on
        (one computed meanwhile is withheld), then the subscriptions, then the token (:mod:`.standby`)."""
        loop = self._event_loop
        if answering and loop is not None:
            if self._watch is not None:
                self._watch.answering(True)
            self.answering = True
            for car in self.cars.values():
                car.listen(self._push(car.name, loop))
            return
        self.answering = False
        if self.role is not None and self.role.is_standby:
            for car in self.cars.values():
                car.quiet()
        if self._watch is not None:
            self._watch.answering(False)

    def stop(self) -> None:
        """End :meth:`serve` (from the event loop's thread)."""
        self.loop.stop()

    @property
    def batch_sizes(self) -> collections.deque[int]:
        """Frames per batch, the recent batches (a batch is one or more model calls: :meth:`figures`)."""
        return self.loop.batch_sizes

    @property
    def batch_s(self) -> collections.deque[float]:
        """Seconds per batch, from its taking to its commands, the recent batches."""
        return self.loop.batch_s

    @property
    def batches(self) -> int:
        """Batches inferred and answered."""
        return self.loop.batches

    @property
    def model_calls(self) -> int | None:
        """Calls of the model runtime, as the model counts them (:attr:`.BatchPilot.calls`); ``None`` for a
        model that does not count them."""
        calls = getattr(self.model, "calls", None)
        return calls if isinstance(calls, int) else None

    def figures(self) -> ServerFigures:
        """The server's figures now, each named as what it counts (:class:`.ServerFigures`)."""
        return ServerFigures.of(self.loop, self.model, self.counters(), withheld=getattr(self, "withheld", 0))

    def counters(self) -> dict[str, dict[str, int]]:
        """Per car: the batcher's counters plus ``answered`` (commands sent), ``late`` (of those, sent when their
        frame was already older than ``max_age_s``: the car's failsafe holds regardless), ``refused`` (frames the
        channel contract refused) and ``wrong_frames`` (not the model's frame size)."""
        out = self.batcher.counters()
        for name, car in self.cars.items():
            row = out.setdefault(name, {"frames": 0, "replaced": 0, "too_old": 0, "batched": 0})
            row["answered"] = car.answered
            row["late"] = car.late
            row["refused"] = car.refused()
            row["wrong_frames"] = car.wrong_frames
        return out

    def close(self) -> None:
        """Undeclare every car's channels, stop the worker thread and close the session (if the server opened
        it)."""
        for car in self.cars.values():
            car.close()
        self.loop.close()
        if self._owned:
            try:
                self.session.close()
            except Exception:  # pragma: no cover
                pass
