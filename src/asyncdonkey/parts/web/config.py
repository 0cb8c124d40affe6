"""``WebConfig``: every setting of the :class:`~.controller.WebController`, its default and its check, in one place.

Why a separate object: a maintainer learns what is settable from this one list instead of the controller's
state; the settings are checked once, when the config is made (a bad one is refused with a one-line
:class:`~.auth.WebConfigError` naming it, before anything listens); and a frozen config can be shared between
cars and tests and varied with :func:`dataclasses.replace`. What the controller is *wired to* (the vehicle for
its health strip, the steering and throttle parts ``/calibrate`` adjusts) is not a setting: the controller
takes those itself.
"""

from __future__ import annotations

import math
import ssl
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Final, TextIO

from ..control import DRIVE_MODES, USER, normalise_mode
from .auth import WebConfigError, is_loopback
from .guard import (
    DEFAULT_BACKLOG,
    DEFAULT_HEADER_TIMEOUT_S,
    DEFAULT_MAX_CONNECTIONS,
    DEFAULT_RESERVE_FDS,
    check_limits,
)

__all__ = ["NEW_TOKEN", "WEB_SETTINGS", "NewToken", "WebConfig"]


class NewToken:
    """The type of :data:`NEW_TOKEN`."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "NEW_TOKEN"


#: The default ``token``: a fresh random token each time the server starts.
NEW_TOKEN: Final = NewToken()


@dataclass(frozen=True, slots=True)
class WebConfig:
    """The web controller's settings (``docs/web.md``, "Options"). Made, checked, then never changed.

    Args:
        port: TCP port (Donkeycar's ``WEB_CONTROL_PORT``, 8887); 0 picks a free one (then ``WebController.port``).
        mode: the drive mode at start (Donkeycar's ``WEB_INIT_MODE``).
        modes: the drive modes the page may choose (without a pilot: ``("user",)``); others are refused.
        host: address to listen on; the default, every interface, is what a phone on the car's Wi-Fi needs.
        token: the access token; by default (:data:`NEW_TOKEN`) a new random one per start. ``None`` disables the
            check and is refused unless ``host`` is a loopback address.
        max_throttle: the page's throttle is multiplied by this (like ``JOYSTICK_MAX_THROTTLE``).
        idle_release_s: a driver silent this long loses control to the next client that drives.
        jpeg_quality: quality of the video's JPEGs (1..100).
        announce: where the drive URL (and QR code) is printed at start; ``None``: only logged.
        qr: print a QR code of the URL (default: when ``announce`` is a terminal).
        ssl_context: serve HTTPS (phones grant the screen wake lock and motion sensors only to secure pages).
        health_every_s: how often the health strip is pushed to the pages.
        header_timeout_s: a connection that has not sent a request with the token this long after it opened
            (slow or missing headers, an unfinished TLS handshake) is closed.
        max_connections: connections open at once; when full, those without the token are closed first (oldest
            first), the driver's never.
        reserve_fds: file descriptors kept free for the car (recordings, logs, devices) below the process's
            ``RLIMIT_NOFILE`` soft limit: no connection is kept that would leave fewer.
        backlog: the listening socket's queue, where new connections wait (holding none of the car's
            descriptors) while there is no room for them.
    """

    port: int = 8887
    mode: str = USER
    modes: Sequence[str] = DRIVE_MODES
    host: str = "0.0.0.0"
    token: str | NewToken | None = NEW_TOKEN
    max_throttle: float = 1.0
    idle_release_s: float = 1.0
    jpeg_quality: int = 80
    announce: TextIO | None = field(default=sys.stderr, compare=False)
    qr: bool | None = None
    ssl_context: ssl.SSLContext | None = field(default=None, compare=False)
    health_every_s: float = 0.5
    header_timeout_s: float = DEFAULT_HEADER_TIMEOUT_S
    max_connections: int = DEFAULT_MAX_CONNECTIONS
    reserve_fds: int = DEFAULT_RESERVE_FDS
    backlog: int = DEFAULT_BACKLOG

    def __post_init__(self) -> None:
        """Check every setting (the error names it) and store ``modes``/``mode`` in their canonical form."""
        host, port, token = self.host, self.port, self.token
        if not (isinstance(port, int) and 0 <= port <= 65535):
            raise WebConfigError(f"WebController: port must be 0..65535, got {port!r}")
        if token is None and not is_loopback(host):
            raise WebConfigError(
                f"WebController: token=None lets anyone who can reach {host}:{port} drive the car; it is allowed "
                "only with a loopback host (host='127.0.0.1'). Keep the default token, or set one."
            )
        if isinstance(token, str) and len(token) < 8:
            raise WebConfigError("WebController: a token must have at least 8 characters")
        max_throttle = self.max_throttle
        if not (isinstance(max_throttle, int | float) and 0.0 <= max_throttle <= 1.0):
            raise WebConfigError(f"WebController: max_throttle must be in [0, 1], got {max_throttle!r}")
        _positive("idle_release_s", self.idle_release_s)
        _positive("health_every_s", self.health_every_s)
        _jpeg_quality(self.jpeg_quality)
        check_limits(self.header_timeout_s, self.max_connections, self.reserve_fds, self.backlog)
        modes = tuple(normalise_mode(m, "WebController modes") for m in self.modes)
        mode = normalise_mode(self.mode, "WebController mode")
        if mode not in modes:
            raise WebConfigError(f"WebController: mode {mode!r} is not one of modes {modes}")
        object.__setattr__(self, "modes", modes)  # frozen: the canonical forms are stored once, here
        object.__setattr__(self, "mode", mode)
        object.__setattr__(self, "max_throttle", float(max_throttle))
        object.__setattr__(self, "idle_release_s", float(self.idle_release_s))
        object.__setattr__(self, "health_every_s", float(self.health_every_s))


#: the names of :class:`WebConfig`'s settings (the keywords ``WebController`` takes besides what it is wired to)
WEB_SETTINGS: Final = frozenset(f.name for f in fields(WebConfig))


def _jpeg_quality(value: Any) -> None:
    try:
        ok = 1 <= int(value) <= 100
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise WebConfigError(f"WebController: jpeg_quality must be 1..100, got {value!r}")


def _positive(name: str, value: Any) -> None:
    if not (isinstance(value, int | float) and value > 0 and math.isfinite(value)):
        raise WebConfigError(f"WebController: {name} must be a positive number, got {value!r}")
