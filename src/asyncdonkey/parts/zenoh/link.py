"""One Zenoh session for a car's (or a pilot's) channels, and the round-trip time that keeps ages true.

A :class:`ZenohLink` owns a Zenoh session and the key prefix its parts publish under (``cars/<name>``); the
publisher and subscriber parts share one link. Zenoh does its I/O on its own threads, so nothing here blocks a
tick.

**Ages across machines.** A value's age at the sender travels in the attachment (see :mod:`.codec`); the
receiver sets the value's origin to ``receipt - age_at_send - transit``. The transit is estimated without any
clock synchronisation: each link answers pings on ``<prefix>/_rtt/ping`` with a pong to the pinger, and the
pinger keeps the round-trip times of its last pings. ``transit_s`` is half the smallest recent round trip
(the least-queued path, as NTP reasons). The age a receiver computes is then off by the difference between
this sample's one-way transit and ``transit_s``: never more than half a round trip on a symmetric link, plus
whatever one-way queueing this sample met beyond the best recent round trip (which makes the age *too young*
by that much; the failsafe window must leave room for it). ``rtt_s`` gives the figures for a status line.

**Closed unless told otherwise.** Zenoh's own defaults listen on every interface and scout by UDP multicast, so
any session on the LAN can find a car and publish to it. A link fills in what its config leaves unset with the
closed choice (:func:`link_config`): listening on 127.0.0.1 only, multicast scouting off. Listening beyond
loopback is written in the config (``listen=["tcp/0.0.0.0:7447"]``, or the car config of ``zenoh-pair``). A
subscriber that takes the car's command channels refuses to start on a session others can publish to
(:meth:`ZenohLink.guard_commands`) unless the link was made with ``insecure=True``.
"""

from __future__ import annotations

import collections
import json
import logging
import struct
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from ...core.buildscope import register_close
from ...errors import AsyncdonkeyError
from ...extras import require
from .certs import log_certificate_problems
from .pairing import COMMAND_CHANNELS

__all__ = ["LOOPBACK_LISTEN", "ZenohConfigError", "ZenohLink", "exposure", "link_config", "zenoh_config"]

logger = logging.getLogger(__name__)

_PING = struct.Struct("<d")
#: Keys under the prefix that belong to the link itself, not to Memory channels.
INTERNAL = "_rtt"
#: where a link listens when its config does not say (per mode, as Zenoh writes its own default): loopback only
LOOPBACK_LISTEN = {"router": ["tcp/127.0.0.1:7447"], "peer": ["tcp/127.0.0.1:0"]}


class ZenohConfigError(AsyncdonkeyError, ValueError):
    """A Zenoh session cannot be configured or opened as asked; the message names the setting or endpoint."""


def zenoh_config(
    config_file: str | Path | None = None,
    *,
    mode: str | None = None,
    connect: Iterable[str] = (),
    listen: Iterable[str] = (),
    multicast_scouting: bool | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Any:
    """A ``zenoh.Config`` as Zenoh users write it: a JSON5 config file, then the usual overrides.

    Args:
        config_file: a Zenoh JSON5 config file (e.g. one written by ``asyncdonkey zenoh-pair``).
        mode: ``"peer"``, ``"client"`` or ``"router"``.
        connect, listen: endpoints such as ``"tcp/192.168.1.20:7447"`` or ``"tls/car1.local:7447"``; when given
            they replace the file's lists.
        multicast_scouting: turn UDP multicast discovery on or off (off in tests and on shared networks).
        extra: more ``path -> value`` settings (``"transport/link/tls/root_ca_certificate": "ca.pem"``).
    """
    zenoh = require("zenoh", "zenoh", "a Zenoh link")

    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise ZenohConfigError(f"Zenoh config file {str(path)!r} not found")
        try:
            cfg = zenoh.Config.from_file(str(path))
        except Exception as exc:
            raise ZenohConfigError(f"Zenoh config file {str(path)!r}: {exc}") from None
    else:
        cfg = zenoh.Config()
    settings: dict[str, Any] = {}
    if mode is not None:
        if mode not in ("peer", "client", "router"):
            raise ZenohConfigError(f"Zenoh mode must be 'peer', 'client' or 'router', got {mode!r}")
        settings["mode"] = mode
    connect, listen = list(connect), list(listen)
    if connect:
        settings["connect/endpoints"] = connect
    if listen:
        settings["listen/endpoints"] = listen
    if multicast_scouting is not None:
        settings["scouting/multicast/enabled"] = bool(multicast_scouting)
    settings.update(extra or {})
    for key, value in settings.items():
        try:
            cfg.insert_json5(key, json.dumps(value))
        except Exception as exc:
            raise ZenohConfigError(f"Zenoh setting {key!r} = {value!r}: {exc}") from None
    return cfg


def _json(cfg: Any, key: str) -> Any:
    try:
        return json.loads(cfg.get_json(key))
    except Exception:
        return None


def _loopback(endpoint: str) -> bool:
    _, _, address = endpoint.partition("/")
    host = address.rsplit(":", 1)[0].strip("[]").split("#")[0]
    return host in ("localhost", "::1") or host.startswith("127.")


def link_config(config: Any = None) -> Any:
    """The ``zenoh.Config`` a :class:`ZenohLink` opens: ``config`` (a ``zenoh.Config``, filled in where it is;
    a config file; or ``None``) with unset listen endpoints made loopback only (:data:`LOOPBACK_LISTEN`) and
    unset multicast scouting turned off.

    Why: left unset, Zenoh listens on every interface (``tcp/[::]:0``) and scouts by multicast, and a peer that
    scouts connects to every peer it finds; any session on the LAN could then publish to the car. What a config
    says explicitly is kept, and judged by :func:`exposure`. (A ``zenoh.Config`` cannot be copied without
    losing the secrets it holds inline, so it is filled in place.)
    """
    zenoh = require("zenoh", "zenoh", "a Zenoh link")

    if config is None:
        config = zenoh.Config()
    elif isinstance(config, str | Path):
        config = zenoh_config(config)
    if config.get_json("listen/endpoints") == zenoh.Config().get_json("listen/endpoints"):  # unset: the default
        config.insert_json5("listen/endpoints", json.dumps(LOOPBACK_LISTEN))
    if _json(config, "scouting/multicast/enabled") is None:
        config.insert_json5("scouting/multicast/enabled", "false")
    return config


def _endpoints(cfg: Any, kind: str, mode: str) -> list[str]:
    endpoints = _json(cfg, f"{kind}/endpoints") or []
    if isinstance(endpoints, dict):
        endpoints = endpoints.get(mode, [])
    return [str(ep) for ep in endpoints]


def exposure(cfg: Any) -> list[str]:
    """Why sessions other than the intended ones could publish to a session with this config (empty: none).

    An endpoint is closed when it is loopback, when it connects over TLS/QUIC with mutual TLS (to the peer it
    dialled, whose certificate it checks), or when it listens with mutual TLS *and* access rules decide which
    certificate may put what. Anything else lets whoever reaches it publish: plain ``tcp/`` or ``udp/`` on a
    reachable address, TLS without client certificates, and a mutual-TLS listener without access rules (every
    holder of a certificate from its CA). Multicast scouting (Zenoh's default) is open too: the session
    connects to the peers it finds on the LAN. Access rules close everything (they decide who may put what).
    """
    if cfg is None:
        return ["Zenoh's default config (listening on every interface, multicast scouting on)"]
    mode = _json(cfg, "mode") or "peer"
    mtls = bool(_json(cfg, "transport/link/tls/enable_mtls"))
    acl = bool(_json(cfg, "access_control/enabled"))
    reasons = []
    for kind in ("listen", "connect"):
        verb = "listens on" if kind == "listen" else "connects to"
        for ep in _endpoints(cfg, kind, mode):
            scheme = ep.split("/", 1)[0]
            if scheme in ("tls", "quic") and mtls:
                if kind == "listen":
                    reasons.append(
                        f"{verb} {ep} with mutual TLS but no access-control rules: any holder of a certificate"
                        " from its CA could command the car"
                    )
                continue
            if _loopback(ep):
                continue
            how = "without client certificates" if scheme in ("tls", "quic") else "without TLS"
            reasons.append(f"{verb} {ep} {how}")
    if _json(cfg, "scouting/multicast/enabled") is not False:
        reasons.append("scouts by UDP multicast (it connects to the sessions it finds on the LAN)")
    if reasons and acl:
        return []  # the access rules decide who may publish what
    return reasons


class ZenohLink:
    """A Zenoh session plus the key prefix of one car's channels, shared by the parts that use it.

    Args:
        prefix: the key expression the channels live under, e.g. ``"cars/car1"`` (``<prefix>/<channel>``).
        config: a ``zenoh.Config`` (see :func:`zenoh_config`), a config file path, or ``None``: peer mode,
            listening on 127.0.0.1 only (a free port), multicast scouting off. Whatever the config leaves unset
            is filled in the same way (:func:`link_config`); listening beyond loopback is said explicitly.
        session: an already open ``zenoh.Session`` to use instead (the link then never closes it, and takes its
            owner's word for how open it is: no checks).
        rtt_window: how many recent round trips ``transit_s`` is estimated from.
        insecure: let subscribers take the car's command channels even though others can publish to this
            session (:attr:`exposure` is not empty); they then only warn. For an isolated bench network.

    The session opens in the constructor, so a wrong endpoint or certificate fails when the car is built, not
    on its first tick. Parts take the link with :meth:`acquire` and give it back with :meth:`release`; the
    session closes when the last one is released.
    """

    def __init__(
        self,
        prefix: str,
        config: Any = None,
        *,
        session: Any = None,
        rtt_window: int = 16,
        insecure: bool = False,
    ) -> None:
        zenoh = require("zenoh", "zenoh", "a Zenoh link")

        prefix = prefix.strip("/")
        if not prefix or any(c in prefix for c in "*$?#"):
            raise ZenohConfigError(f"ZenohLink: prefix must be a plain key expression like 'cars/car1', got {prefix!r}")
        self.prefix = prefix
        self.now: Callable[[], float] = time.monotonic
        self.insecure = bool(insecure)
        self._owned = session is None
        #: the config the session was opened with (``None`` for a session given to the link)
        self.config: Any = None
        if session is None:
            self.config = config = link_config(config)
            #: why others than the intended peers could publish to this session (``[]``: nobody can)
            self.exposure = exposure(config)
            #: certificates of the config outside their validity window on this clock (logged: :mod:`.certs`)
            self.certificate_problems = log_certificate_problems(config, f"ZenohLink {prefix!r}")
            try:
                session = zenoh.open(config)
            except Exception as exc:
                raise ZenohConfigError(f"ZenohLink {prefix!r}: cannot open a Zenoh session: {exc}") from None
        else:
            self.exposure = []  # a session given to us: its owner knows how it is configured
            self.certificate_problems = []
        self.session = session
        self._users = 0
        self._lock = threading.Lock()
        self._rtts: collections.deque[float] = collections.deque(maxlen=rtt_window)
        self.pings_sent = 0
        self.pongs_received = 0
        self._closed = False
        self._decls: list[Any] = []
        try:
            self.zid = str(session.zid())
            self._ping_pub = session.declare_publisher(f"{prefix}/{INTERNAL}/ping", express=True)
            self._decls.append(self._ping_pub)
            self._decls.append(
                session.declare_subscriber(
                    f"{prefix}/{INTERNAL}/ping", self._on_ping, allowed_origin=zenoh.Locality.REMOTE
                )
            )
            self._decls.append(session.declare_subscriber(f"{prefix}/{INTERNAL}/pong/{self.zid}", self._on_pong))
        except BaseException:
            self.close()  # the session we opened has threads that would keep the process alive
            raise
        if self._owned:  # a car whose build() raises after this: `asyncdonkey run` closes the session
            register_close(f"the Zenoh session of ZenohLink {prefix!r}", self.close)

    def key(self, channel: str) -> str:
        """The key expression of a Memory channel: ``<prefix>/<channel>``."""
        return f"{self.prefix}/{channel.strip('/')}"

    def guard_commands(self, channels: Iterable[str], who: str) -> None:
        """Refuse (:class:`ZenohConfigError`) to let ``who`` take the car's command channels from a session that
        others can publish to; warn for other channels, or for commands on an ``insecure=True`` link.

        Why refuse rather than warn: a warning in a car's log does not stop a stranger's ``pilot/throttle``;
        the car is then one put away from being steered by anyone who reaches the session.
        """
        if not self.exposure:
            return
        commands = [ch for ch in channels if ch in COMMAND_CHANNELS]
        why = "; ".join(self.exposure)
        if commands and not self.insecure:
            raise ZenohConfigError(
                f"{who}: refusing to take the command channels {commands} from the network: this session {why},"
                " and it has no access-control rules, so others could steer the car. Use the configs of"
                " `asyncdonkey zenoh-pair` (mutual TLS and access rules, docs/scale-out.md) or listen on"
                " 127.0.0.1 only; on an isolated bench network, make the link with ZenohLink(..., insecure=True)."
            )
        logger.warning(
            "%s: anyone who can reach this session can write these channels (it %s)%s. For commands, use the"
            " configs of `asyncdonkey zenoh-pair` (docs/scale-out.md).",
            who,
            why,
            " (insecure=True)" if commands else "",
        )

    # -- round trip ------------------------------------------------------------------------------------
    def ping(self) -> None:
        """Send one ping; every other link on the prefix answers, and :attr:`transit_s` learns the round trip."""
        if self._closed:
            return
        self.pings_sent += 1
        self._ping_pub.put(_PING.pack(time.monotonic()) + self.zid.encode())

    def _on_ping(self, sample: Any) -> None:
        data = sample.payload.to_bytes()
        if len(data) <= _PING.size or self._closed:
            return
        zid = data[_PING.size :].decode("ascii", errors="replace")
        if not zid.isalnum():
            return
        try:
            self.session.put(f"{self.prefix}/{INTERNAL}/pong/{zid}", data[: _PING.size], express=True)
        except Exception:  # the session is closing
            pass

    def _on_pong(self, sample: Any) -> None:
        data = sample.payload.to_bytes()
        if len(data) != _PING.size:
            return
        rtt = time.monotonic() - _PING.unpack(data)[0]
        if 0 <= rtt < 60:
            with self._lock:
                self._rtts.append(rtt)
                self.pongs_received += 1

    @property
    def transit_s(self) -> float:
        """Estimated one-way transit (s): half the smallest recent round trip; 0 before the first pong."""
        with self._lock:
            return min(self._rtts) / 2 if self._rtts else 0.0

    def rtt_s(self) -> tuple[float, float] | None:
        """``(smallest, newest)`` recent round trip in seconds, or ``None`` before the first pong."""
        with self._lock:
            return (min(self._rtts), self._rtts[-1]) if self._rtts else None

    # -- lifetime --------------------------------------------------------------------------------------
    def acquire(self) -> ZenohLink:
        with self._lock:
            if self._closed:
                raise ZenohConfigError(f"ZenohLink {self.prefix!r} is closed")
            self._users += 1
        return self

    def release(self) -> None:
        with self._lock:
            self._users -= 1
            last = self._users <= 0
        if last:
            self.close()

    def close(self) -> None:
        """Undeclare everything and close the session (if the link opened it). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for d in reversed(self._decls):  # the subscribers, then the publisher
            try:
                d.undeclare()
            except Exception:
                pass
        if self._owned:
            try:
                self.session.close()
            except Exception:  # pragma: no cover - closing twice or during interpreter exit
                pass

    @property
    def closed(self) -> bool:
        return self._closed

    def __repr__(self) -> str:
        return f"ZenohLink({self.prefix!r}, zid={self.zid})"
