"""``WebController``: drive, record and hand over to the pilot from a phone or laptop browser.

Donkeycar's ``LocalWebController`` with its part contract and web API (so its pages and scripts keep working),
rebuilt on the drive loop:

* **No thread.** The aiohttp server lives in the part's ``async update()`` task on the drive loop's event loop;
  a command is applied the moment its message is read, and ``shutdown()`` closes the server.
* **Commands know their age.** ``output_origin()`` is the arrival time of the active driver's latest command,
  so a ``PWMThrottle`` wired with ``throttle@age`` stops the car when the driving page goes quiet, hidden or
  away, exactly as for every other controller (``docs/web.md``, "Deadman").
* **One driver at a time**, others watch (:mod:`.desk`); anyone can stop.
* **Video at one encode per new frame**, shared by all viewers (:mod:`.video`).
* **A token per start** (:mod:`.auth`), printed as a URL and a QR code.
* **Floods cannot lock the driver out** (:mod:`.guard`): a connection must present the token within
  ``header_timeout_s``; at most ``max_connections``; ``reserve_fds`` descriptors stay free for the car's files;
  the connections shed to make room are those without the token, never the driver's.

Part contract (Donkeycar's)::

    inputs  cam/image_array, tub/num_records, user/mode, recording
    outputs user/angle, user/throttle, user/mode, recording, web/buttons

HTTP API (Donkeycar's, port 8887): ``/`` → ``/drive``; ``GET /drive`` the page; ``POST /drive`` and WebSocket
``/wsDrive`` take ``{"angle", "throttle", "drive_mode", "recording", "buttons"}``; the WebSocket pushes
``driveMode``, ``recording`` and ``num_records``; ``/video`` the MJPEG stream; ``/calibrate`` and
``/wsCalibrate`` the PWM calibration. Ours on top: ``{"stop": true}``, ``{"release": true}``, pushes of
``control`` (``you``/``other``/``free``), ``health`` and ``error``; ``GET /status`` (JSON).

Every value a client sends goes through the car's contracts at the boundary (:mod:`.intake`: the
controller's :class:`~asyncdonkey.contracts.Gate`, ``"web"``): a bad one is answered (400, or an ``error`` push
on a socket kept open), counted in ``/status`` under ``refused_values``, and applied as nothing at all.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import ssl
import sys
import threading
from collections import deque
from collections.abc import Callable, Sequence
from importlib import resources
from typing import Any, Final, TextIO

from aiohttp import WSMsgType, web

from ...clock import Clock, get_clock
from ...contracts import Contracts, Gate
from ...periodic import Periodic
from ...ratelimit import LogThrottle
from ..control import DRIVE_MODES, USER, normalise_mode
from .addresses import WILDCARD_VERSIONS, DriveUrl, InterfaceTable, drive_urls, system_interfaces
from .auth import TOKEN_PARAM, Access, Sessions, WebConfigError, is_loopback, new_token, origin_allowed
from .calibrate import (
    CALIBRATION,
    CalibrationError,
    admit_config,
    apply_calibration,
    current_calibration,
    why_not_stopped,
)
from .desk import Command, CommandError, Desk
from .guard import (
    DEFAULT_BACKLOG,
    DEFAULT_HEADER_TIMEOUT_S,
    DEFAULT_MAX_CONNECTIONS,
    DEFAULT_RESERVE_FDS,
    ConnectionGuard,
    check_limits,
)
from .health import vehicle_health
from .intake import COMMAND, MAX_MESSAGE_BYTES, Intake
from .video import FrameHub

__all__ = ["NEW_TOKEN", "WEB_INPUTS", "WEB_OUTPUTS", "WebController"]

logger = logging.getLogger(__name__)

WEB_INPUTS: Final = ("cam/image_array", "tub/num_records", "user/mode", "recording")
WEB_OUTPUTS: Final = ("user/angle", "user/throttle", "user/mode", "recording", "web/buttons")


class _NewToken:
    def __repr__(self) -> str:
        return "NEW_TOKEN"


#: The default ``token``: a fresh random token each time the server starts.
NEW_TOKEN: Final = _NewToken()

_STATIC_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}
_CSP = (
    "default-src 'self'; img-src 'self' data:; connect-src 'self' ws: wss:; style-src 'self'; script-src 'self'; "
    "frame-ancestors 'none'"
)
#: an idle keep-alive connection (its requests had the token, so the guard never sheds it) ends after this
_KEEPALIVE_S = 60.0
#: a WebSocket frame larger than this closes the socket (1009): aiohttp must buffer a frame to read it. Below it,
#: a message over ``MAX_MESSAGE_BYTES`` is refused with an ``error`` push and the socket stays open.
_WS_FRAME_LIMIT = 1 << 20


def _load_static() -> dict[str, tuple[bytes, str]]:
    """The page's files, read once from the package (a car has no internet: nothing comes from a CDN)."""
    out: dict[str, tuple[bytes, str]] = {}
    for entry in resources.files(__package__).joinpath("static").iterdir():
        suffix = "." + entry.name.rsplit(".", 1)[-1]
        if entry.is_file() and suffix in _STATIC_TYPES:
            out[entry.name] = (entry.read_bytes(), _STATIC_TYPES[suffix])
    return out


class WebController:
    """A browser as the car's controller (see the module docstring and ``docs/web.md``).

    Args:
        port: TCP port (Donkeycar's ``WEB_CONTROL_PORT``, 8887); 0 picks a free one (see :attr:`port`).
        mode: the drive mode at start (Donkeycar's ``WEB_INIT_MODE``).
        modes: the drive modes the page may choose (without a pilot: ``("user",)``); others are refused.
        host: address to listen on; the default, every interface, is what a phone on the car's Wi-Fi needs.
        token: the access token; by default a new random one per start. ``None`` disables the check and is
            refused unless ``host`` is a loopback address.
        vehicle: the Vehicle, for the page's health strip (its profiler); or give ``status``.
        status: a callable returning a JSON-able dict shown as the health strip (overrides ``vehicle``).
        steering, throttle: the ``PWMSteering`` / ``PWMThrottle`` parts ``/calibrate`` adjusts.
        max_throttle: the page's throttle is multiplied by this (like ``JOYSTICK_MAX_THROTTLE``).
        idle_release_s: a driver silent this long loses control to the next client that drives.
        jpeg_quality: quality of the video's JPEGs.
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

    def __init__(
        self,
        port: int = 8887,
        mode: str = USER,
        *,
        modes: Sequence[str] = DRIVE_MODES,
        host: str = "0.0.0.0",
        token: str | _NewToken | None = NEW_TOKEN,
        vehicle: Any = None,
        status: Callable[[], dict[str, Any]] | None = None,
        steering: Any = None,
        throttle: Any = None,
        max_throttle: float = 1.0,
        idle_release_s: float = 1.0,
        jpeg_quality: int = 80,
        announce: TextIO | None = sys.stderr,
        qr: bool | None = None,
        ssl_context: ssl.SSLContext | None = None,
        health_every_s: float = 0.5,
        header_timeout_s: float = DEFAULT_HEADER_TIMEOUT_S,
        max_connections: int = DEFAULT_MAX_CONNECTIONS,
        reserve_fds: int = DEFAULT_RESERVE_FDS,
        backlog: int = DEFAULT_BACKLOG,
    ) -> None:
        if not (isinstance(port, int) and 0 <= port <= 65535):
            raise WebConfigError(f"WebController: port must be 0..65535, got {port!r}")
        if token is None and not is_loopback(host):
            raise WebConfigError(
                f"WebController: token=None lets anyone who can reach {host}:{port} drive the car; it is allowed "
                "only with a loopback host (host='127.0.0.1'). Keep the default token, or set one."
            )
        if isinstance(token, str) and len(token) < 8:
            raise WebConfigError("WebController: a token must have at least 8 characters")
        if not (isinstance(max_throttle, int | float) and 0.0 <= max_throttle <= 1.0):
            raise WebConfigError(f"WebController: max_throttle must be in [0, 1], got {max_throttle!r}")
        if not (health_every_s > 0 and math.isfinite(health_every_s)):
            raise WebConfigError(f"WebController: health_every_s must be a positive number, got {health_every_s!r}")
        check_limits(header_timeout_s, max_connections, reserve_fds, backlog)
        self.host = host
        self.port = port
        self._token_setting = token
        self.token: str | None = None  # the token in force (set when the server starts)
        self.url: str | None = None  # the drive URL with the token, once listening
        self.vehicle = vehicle
        self._status = status if status is not None else (lambda: vehicle_health(vehicle)) if vehicle else None
        self.steering = steering
        self.throttle_part = throttle
        self.max_throttle = float(max_throttle)
        self.announce = announce
        self.qr = qr
        #: lists the interfaces whose addresses are printed (tests give a fake table)
        self.interfaces: InterfaceTable = system_interfaces
        self.ssl_context = ssl_context
        self.health_every_s = float(health_every_s)
        self.backlog = backlog
        #: connection admission: header deadline, cap, descriptor reserve (counters in ``/status``)
        self.guard = ConnectionGuard(header_timeout_s, max_connections, reserve_fds)
        self.outputs: list[str] = list(WEB_OUTPUTS)
        self.inputs: list[str] = list(WEB_INPUTS)

        self.angle = 0.0
        self.throttle = 0.0
        self.modes = tuple(normalise_mode(m, "WebController modes") for m in modes)
        self.mode = normalise_mode(mode, "WebController mode")
        if self.mode not in self.modes:
            raise WebConfigError(f"WebController: mode {self.mode!r} is not one of modes {self.modes}")
        self.recording = False
        self.num_records = 0
        self._mode_latch: str | None = None
        self._recording_latch: bool | None = None
        self._buttons: dict[str, bool] = {}

        self.desk = Desk(idle_release_s)
        #: the latest calibration requests, accepted or refused: when, who, what was asked, what changed, why not
        self.calibrations: deque[dict[str, Any]] = deque(maxlen=100)
        self._who: dict[object, str] = {}  # a page -> how the logs name it (its address)
        self._calibration_log = LogThrottle(1.0)
        self.hub = FrameHub(jpeg_quality)
        self.commands = 0  # drive commands applied
        self.bad_commands = 0  # messages refused (a bad value, not JSON, too large, ...)
        self.gate: Gate
        self.intake: Intake
        self.use_contracts(Contracts())  # until Vehicle.add gives the car's own
        self.ticks = 0
        self.last_health: dict[str, Any] | None = None
        #: set (from the loop) once the server listens; threads may wait on it
        self.listening = threading.Event()
        self._origin: float | None = None
        self._clients: dict[web.WebSocketResponse, str] = {}  # socket -> role last told
        self._tasks: set[asyncio.Task[Any]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._clock: Clock | None = None
        self._stop: asyncio.Event | None = None
        self._served: asyncio.Future[None] | None = None
        self._access: Access | None = None
        self._sessions = Sessions(port, secure=ssl_context is not None)
        self._static = _load_static()
        self._log = LogThrottle(5.0)

    # ================================================================================== part contract
    def use_contracts(self, contracts: Contracts) -> None:
        """Check what clients send against ``contracts`` (the car's: ``Vehicle.add`` calls this). Until then,
        and for a controller never added to a vehicle, the default contracts apply."""
        self.gate = contracts.gate("web")
        self.intake = Intake(self.gate, self.modes, self._now)

    @property
    def refused_values(self) -> dict[str, dict[str, int]]:
        """Values refused at the web boundary, ``{channel: {reason: count}}`` (also in ``/status``)."""
        return self.gate.counts()

    def run(
        self, img_arr: Any = None, num_records: Any = 0, mode: Any = None, recording: Any = None
    ) -> tuple[float, float, str, bool, dict[str, bool]]:
        """One tick: take the image and the car's state, return ``angle, throttle, mode, recording, buttons``."""
        self.hub.offer(img_arr)
        self.ticks += 1
        if self.desk.driver is not None and self.desk.expire(self._now()):
            self._on_release("went quiet")
        changes: dict[str, Any] = {}
        if mode is not None:
            m = normalise_mode(mode, "WebController input 'user/mode'")
            if m != self.mode:
                self.mode = m
                changes["driveMode"] = m
        if self._mode_latch is not None:
            self.mode, self._mode_latch = self._mode_latch, None
            changes["driveMode"] = self.mode
        if recording is not None and bool(recording) != self.recording:
            self.recording = bool(recording)
            changes["recording"] = self.recording
        if self._recording_latch is not None:
            self.recording, self._recording_latch = self._recording_latch, None
            changes["recording"] = self.recording
        if num_records is not None and num_records != self.num_records:
            before, self.num_records = self.num_records, int(num_records)
            # every tenth record, as Donkeycar pushes it; a count that jumps past a multiple of ten (the writer
            # counts records once they are on disk, two at a time now and then) still crosses it
            if self.recording and self.num_records // 10 != before // 10:
                changes["num_records"] = self.num_records
        # Donkeycar's button latch: a press is reported on one tick, then as released on the next
        buttons = self._buttons
        self._buttons = {name: False for name, pressed in buttons.items() if pressed}
        if changes:
            self._broadcast(changes)
        return self.angle, self.throttle, self.mode, self.recording, buttons

    run_threaded = run

    def output_origin(self) -> float | None:
        """Arrival time of the driver's latest command (server start before any): what ``@age`` measures."""
        return self._origin

    async def update(self) -> None:
        """Serve until :meth:`shutdown` (a background task beside the ticks)."""
        loop = self._loop = asyncio.get_running_loop()
        clock = self._clock = get_clock(loop)
        self._stop = asyncio.Event()
        self._served = loop.create_future()
        self.token = new_token() if isinstance(self._token_setting, _NewToken) else self._token_setting
        runner = web.AppRunner(self._make_app(), access_log=None, shutdown_timeout=1.0, keepalive_timeout=_KEEPALIVE_S)
        try:
            await runner.setup()
            self.port = await self._listen(runner)
            assert self._access is not None
            self._access.cookie = f"asyncdonkey-token-{self.port}"
            self._sessions.cookie = f"asyncdonkey-session-{self.port}"
            self._origin = clock.now()
            urls = await loop.run_in_executor(None, self._urls)  # lists the interfaces (a netlink round trip)
            self.url = urls[0].url
            self._announce(urls)
            self.listening.set()
            tasks = [
                asyncio.create_task(self.hub.run(), name="web video encoder"),
                asyncio.create_task(self._health_loop(), name="web health"),
            ]
            try:
                await self._stop.wait()
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
        finally:
            await self._close(runner)
            self.listening.clear()
            if not self._served.done():
                self._served.set_result(None)

    async def shutdown(self, timeout: float = 2.0) -> None:
        """Close every connection and stop listening (waits up to ``timeout`` seconds)."""
        if self._stop is None or self._served is None:
            return
        self._stop.set()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(self._served), timeout)

    async def _listen(self, runner: web.AppRunner) -> int:
        """Listen, the connection guard accepting (TLS too: the guard hands the socket over for the handshake,
        so a connection that never completes one is seen, counted and timed out like any other). Returns the
        port."""
        assert runner.server is not None
        try:
            bound = await self.guard.start(
                runner.server, self.host, self.port, backlog=self.backlog, ssl_context=self.ssl_context
            )
        except OSError as exc:
            raise WebConfigError(f"WebController: cannot listen on {self.host}:{self.port}: {exc}") from exc
        return int(bound[0][1])

    async def _close(self, runner: web.AppRunner) -> None:
        await self.guard.stop()  # no new connections; aiohttp's cleanup below closes the open ones
        await self.hub.close()
        for ws in list(self._clients):
            with contextlib.suppress(Exception):
                await ws.close(code=1001, message=b"the car is shutting down")
        for t in list(self._tasks):
            t.cancel()
        await runner.cleanup()

    # ================================================================================== commands
    def _now(self) -> float:
        clock = self._clock
        if clock is None:
            clock = self._clock = get_clock()
        return clock.now()

    def apply(self, client: object | None, cmd: Command) -> str:
        """Apply one command from ``client``; returns its role afterwards (``you``, ``other`` or ``free``).

        ``client`` ``None`` is a script without a session: it never holds control (its drive commands apply only
        while nobody holds it, and its stop frees control instead of taking it). Raises
        :class:`~.desk.CommandError` for a drive mode not in ``modes`` (nothing of the command is applied).
        """
        if cmd.mode is not None and cmd.mode not in self.modes:
            raise CommandError(f"web command: drive mode {cmd.mode!r} is not available here (modes: {self.modes})")
        now = self._now()
        before = self.desk.driver
        if cmd.stop:
            if client is None:
                self.desk.free()
            else:
                self.desk.claim(client, now, force=True)
            self.throttle = 0.0
            self._mode_latch = USER  # the pilot loses the car too
            self._origin = now
            logger.warning("web: stop from %s", self._describe(client))
        if cmd.release and client is not None and self.desk.release(client):
            self._on_release("released")
        if cmd.drives:
            if not self._may_drive(client, now):
                return "other"
            if cmd.angle is not None:
                self.angle = cmd.angle
            if cmd.throttle is not None:
                self.throttle = 0.0 if cmd.stop else cmd.throttle * self.max_throttle
            if cmd.mode is not None and not cmd.stop:
                self.mode = self._mode_latch = cmd.mode
            if cmd.recording is not None:
                self.recording = self._recording_latch = cmd.recording
            if cmd.buttons:
                for name, pressed in cmd.buttons.items():
                    if pressed:
                        self._buttons[name] = True
            self._origin = now
            self.commands += 1
        if self.desk.driver is not before:
            self._push_roles()
        return self.desk.role(client, now)

    def _may_drive(self, client: object | None, now: float) -> bool:
        """Control for this command: claimed by a client (a socket, a session), only borrowed by one without."""
        if client is not None:
            return self.desk.claim(client, now)
        if self.desk.is_free(now):
            return True
        self.desk.refused += 1
        return False

    def _on_release(self, why: str) -> None:
        """The driver let go: neutral command, but with the *old* arrival time, so the failsafe sees its age."""
        self.throttle = 0.0
        self.angle = 0.0
        logger.info("web: the driver %s; control is free", why)
        self._push_roles()

    # ================================================================================== server
    def _make_app(self) -> web.Application:
        self._access = Access(self.token, self.port, on_admit=self.guard.admit)
        # a body over the message limit is refused when read (never buffered whole): see _read_body
        app = web.Application(
            middlewares=[self._access.middleware, _security_headers], client_max_size=MAX_MESSAGE_BYTES
        )
        app.router.add_get("/", self._root)
        app.router.add_get("/drive", self._page("drive.html"))
        app.router.add_post("/drive", self._post_drive)
        app.router.add_get("/wsDrive", self._ws_drive)
        app.router.add_get("/calibrate", self._page("calibrate.html"))
        app.router.add_get("/wsCalibrate", self._ws_calibrate)
        app.router.add_get("/video", self.hub.stream)
        app.router.add_get("/status", self._get_status)
        app.router.add_get("/static/{name}", self._get_static)
        return app

    async def _root(self, request: web.Request) -> web.StreamResponse:
        raise web.HTTPFound("/drive")

    def _page(self, name: str) -> Callable[[web.Request], Any]:
        async def handler(request: web.Request) -> web.StreamResponse:
            body, ctype = self._static[name]
            return web.Response(body=body, content_type=ctype, headers={"Cache-Control": "no-cache"})

        return handler

    async def _get_static(self, request: web.Request) -> web.StreamResponse:
        found = self._static.get(request.match_info["name"])
        if found is None:
            raise web.HTTPNotFound()
        body, ctype = found
        return web.Response(body=body, content_type=ctype, headers={"Cache-Control": "no-cache"})

    def state(self, client: object = None) -> dict[str, Any]:
        """What ``/status`` returns: the controller's state, the video counters and the health figures."""
        now = self._now()
        return {
            "angle": self.angle,
            "throttle": self.throttle,
            "driveMode": self.mode,
            "recording": self.recording,
            "num_records": self.num_records,
            "control": self.desk.role(client, now),
            "command_age_s": (now - self._origin) if self._origin is not None else None,
            "commands": self.commands,
            "refused": self.desk.refused,
            "bad_commands": self.bad_commands,
            "refused_values": self.gate.counts(),
            "viewers": self.hub.viewers,
            "encodes": self.hub.encodes,
            "health": self.last_health,
            "connections": self.guard.counters(),
        }

    async def _get_status(self, request: web.Request) -> web.StreamResponse:
        return web.json_response(self.state(self._session_client(request)))

    def _session_client(self, request: web.Request) -> str | None:
        """The ``POST`` client a request comes from: its session, or ``None`` (no session: never holds control)."""
        session = self._sessions.of(request)
        return None if session is None else f"session:{session}"

    async def _post_drive(self, request: web.Request) -> web.StreamResponse:
        _check_origin(request)
        client = self._session_client(request)
        try:
            cmd = self.intake.command(self.intake.decode(await self._read_body(request)))
            role = self.apply(client, cmd)
        except CommandError as exc:
            self.bad_commands += 1
            resp = web.json_response({"error": str(exc)}, status=400)
        else:
            if role == "other" and cmd.drives:
                resp = web.json_response({"control": role, "error": "another client is driving"}, status=409)
            else:
                resp = web.json_response({"control": role})
        if client is None:
            self._sessions.issue(resp)  # a client that keeps it can hold control from its next command
        return resp

    async def _read_body(self, request: web.Request) -> bytes:
        """The request's body, up to :data:`MAX_MESSAGE_BYTES`: a larger one is a refused value (400), never
        held whole (aiohttp reads the rest after the answer and throws it away, within its lingering time)."""
        try:
            return await request.read()
        except web.HTTPRequestEntityTooLarge:
            raise self.intake.refuse(COMMAND, "size", f"a body over {MAX_MESSAGE_BYTES} bytes") from None

    async def _ws_drive(self, request: web.Request) -> web.StreamResponse:
        _check_origin(request)
        ws = web.WebSocketResponse(heartbeat=2.0, max_msg_size=_WS_FRAME_LIMIT)
        await ws.prepare(request)
        self._page_opened(ws, request)
        role = self.desk.role(ws, self._now())
        self._clients[ws] = role
        hello: dict[str, Any] = {
            "driveMode": self.mode,
            "recording": self.recording,
            "num_records": self.num_records,
            "control": role,
            "modes": list(self.modes),
        }
        if self.last_health is not None:
            hello["health"] = self.last_health
        await ws.send_json(hello)
        try:
            async for msg in ws:
                self._on_message(ws, msg)
        finally:
            self._clients.pop(ws, None)
            if self._page_closed(ws):
                self._on_release("closed the page")
        return ws

    def _on_message(self, ws: web.WebSocketResponse, msg: Any) -> None:
        """One message from a drive page: applied, or refused with an ``error`` push; the socket stays open
        whatever it carried (a dropped driver's socket would release control: one bad value must not)."""
        try:
            role = self.apply(ws, self.intake.command(self.intake.decode(_text(msg, self.intake))))
        except CommandError as exc:
            self.bad_commands += 1
            self._send(ws, {"error": str(exc)})
            return
        except Exception as exc:  # a bug here must not drop the driver: say so loudly, keep the socket
            self._internal_error(ws, exc)
            return
        if self._clients.get(ws) != role:
            self._clients[ws] = role
            self._send(ws, {"control": role})

    def _internal_error(self, ws: web.WebSocketResponse, exc: Exception) -> None:
        self.bad_commands += 1
        held = self._log.ready("internal", self._now(), "failures")
        if held is not None:
            logger.error("web: a message could not be handled%s", held, exc_info=exc)
        self._send(ws, {"error": f"web: the car could not handle that message ({type(exc).__name__})"})

    async def _ws_calibrate(self, request: web.Request) -> web.StreamResponse:
        _check_origin(request)
        ws = web.WebSocketResponse(heartbeat=2.0, max_msg_size=_WS_FRAME_LIMIT)
        await ws.prepare(request)
        self._page_opened(ws, request)
        try:
            await ws.send_json({"config": current_calibration(self.steering, self.throttle_part)})
            async for msg in ws:
                for payload in self._on_calibrate_message(ws, msg):
                    await _send_json(ws, payload)
        finally:
            if self._page_closed(ws):
                self._on_release("closed the calibration page")
        return ws

    def _page_opened(self, ws: web.WebSocketResponse, request: web.Request) -> None:
        """A page connected: the desk counts it (a lone page may calibrate), the logs name it by its address."""
        self.desk.opened(ws)
        self._who[ws] = f"page {id(ws):x} from {request.remote or 'an unknown address'}"

    def _page_closed(self, ws: web.WebSocketResponse) -> bool:
        """A page closed; true when it held control (now free)."""
        self._who.pop(ws, None)
        return self.desk.closed(ws)

    def _describe(self, client: object) -> str:
        """How the logs name a client: a page by its address, a ``POST`` script by its session."""
        return self._who.get(client) or _name(client)

    def _on_calibrate_message(self, ws: web.WebSocketResponse, msg: Any) -> list[dict[str, Any]]:
        """One message from the calibration page (``config``, then test ``angle``/``throttle``); the answers."""
        try:
            data = self.intake.decode(_text(msg, self.intake), CALIBRATION)
            drive = {k: data[k] for k in ("angle", "throttle") if k in data}
            cmd = self.intake.command(drive) if drive else None  # admitted first: the message is taken whole
            out: list[dict[str, Any]] = []
            if "config" in data:
                out.append({"config": self.calibrate(ws, data["config"])})
            if cmd is not None:
                out.append({"control": self.apply(ws, cmd)})
            return out
        except WebConfigError as exc:  # CommandError, CalibrationError
            self.bad_commands += 1
            answer: dict[str, Any] = {"error": str(exc)}
            if isinstance(exc, CalibrationError) and exc.in_force is not None:
                answer["config"] = exc.in_force
            return [answer]
        except Exception as exc:
            self._internal_error(ws, exc)
            return []

    def calibrate(self, client: object, config: object) -> dict[str, int]:
        """Set a calibration (``{"STEERING_LEFT_PWM": 480, ...}``) for ``client``; returns the calibration in force.

        Only the driver (:meth:`~.desk.Desk.why_not_calibrator`; a lone page takes control with it), only while
        the car is disarmed (:func:`~.calibrate.why_not_stopped`), never moving the stopped pulse the drive armed
        the ESC with (the throttle refuses it). Every request, accepted or refused, is logged with who made it
        and what it asked or changed, and kept in :attr:`calibrations`. Raises :class:`CalibrationError` (its
        text is what the client is told), counted at the web gate."""
        now = self._now()
        who = self._describe(client)
        try:
            pulses = admit_config(self.intake, config)  # each refused value is counted by the gate as it goes
        except CalibrationError as exc:
            self._calibration_refused(now, who, config, exc)
            raise
        try:
            refusal = self.desk.why_not_calibrator(client, now)
            if refusal is not None:
                raise CalibrationError(f"calibration: {refusal}", reason="not_driver")
            moving = why_not_stopped(self.throttle, self.mode, self.throttle_part)
            if moving is not None:
                raise CalibrationError(f"calibration: the car must be stopped to calibrate: {moving}", reason="moving")
            before = current_calibration(self.steering, self.throttle_part)
            applied = apply_calibration(self.steering, self.throttle_part, pulses)
        except CalibrationError as exc:
            self.gate.refuse(exc.channel, exc.reason, str(exc), now)
            self._calibration_refused(now, who, pulses, exc)
            raise
        driver = self.desk.driver
        self.desk.claim(client, now)  # the calibrator holds control: a watcher's drive commands are "other"
        if self.desk.driver is not driver:
            self._push_roles()
        changed = {k: [before[k], v] for k, v in applied.items() if before.get(k) != v}
        self.calibrations.append({"t": now, "who": who, "asked": pulses, "changed": changed, "refused": None})
        said = ", ".join(f"{k} {a} -> {b}" for k, (a, b) in changed.items()) or "nothing changed"
        logger.info("web: calibration by %s: %s", who, said)
        return applied

    def _calibration_refused(self, now: float, who: str, asked: object, exc: CalibrationError) -> None:
        """Keep and log a refused calibration with who asked (the log rate-limited per client: one a second)."""
        record = asked if isinstance(asked, dict) else repr(asked)[:80]
        self.calibrations.append({"t": now, "who": who, "asked": record, "changed": {}, "refused": str(exc)})
        more = self._calibration_log.ready(who, now, "refusals")
        if more is not None:
            logger.warning("web: calibration refused for %s (asked %.200s): %s%s", who, record, exc, more)

    # ================================================================================== pushes
    def _send(self, ws: web.WebSocketResponse, payload: dict[str, Any]) -> None:
        """Queue a push to one page; from the loop thread or any other (a tick run with ``executor=True``)."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            here = asyncio.get_running_loop()
        except RuntimeError:
            here = None
        if here is not loop:
            loop.call_soon_threadsafe(self._send, ws, payload)
            return
        task = loop.create_task(_send_json(ws, payload))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _broadcast(self, payload: dict[str, Any]) -> None:
        """Push to every page; safe from the tick (any thread), a no-op before the server runs."""
        loop = self._loop
        if loop is None or loop.is_closed() or not self._clients:
            return
        loop.call_soon_threadsafe(self._broadcast_now, payload)

    def _broadcast_now(self, payload: dict[str, Any]) -> None:
        for ws in list(self._clients):
            self._send(ws, payload)

    def _push_roles(self) -> None:
        now = self._now()
        for ws, told in list(self._clients.items()):
            role = self.desk.role(ws, now)
            if role != told:
                self._clients[ws] = role
                self._send(ws, {"control": role})

    async def _health_loop(self) -> None:
        clock = self._clock
        assert clock is not None
        last_t, last_n = clock.now(), self.ticks
        with Periodic(self.health_every_s) as every:
            while True:
                await every.next()
                now, n = clock.now(), self.ticks
                health: dict[str, Any] = {"hz": round((n - last_n) / (now - last_t), 2) if now > last_t else 0.0}
                last_t, last_n = now, n
                if self._status is not None:
                    try:
                        health.update(self._status())
                    except Exception as exc:  # a status callable must not take the controller down
                        held = self._log.ready("status", now, "failures")
                        if held is not None:
                            logger.error("web: the status callable failed%s: %r", held, exc)
                health["viewers"] = self.hub.viewers
                self.last_health = health
                self._push_roles()
                if self._clients:
                    self._broadcast_now({"health": health})

    # ================================================================================== start-up message
    def _urls(self) -> list[DriveUrl]:
        """The drive URLs to print, the one for the QR code first (:mod:`.addresses`)."""
        scheme = "https" if self.ssl_context is not None else "http"
        query = f"?{TOKEN_PARAM}={self.token}" if self.token else ""
        if self.host in WILDCARD_VERSIONS:
            return drive_urls(scheme, self.port, f"/drive{query}", self.interfaces, None, WILDCARD_VERSIONS[self.host])
        host = f"[{self.host}]" if ":" in self.host else self.host
        return [DriveUrl(f"{scheme}://{host}:{self.port}/drive{query}")]

    def _announce(self, urls: list[DriveUrl]) -> None:
        logger.info("web controller listening on %s:%d", self.host, self.port)
        out = self.announce
        if out is None:
            return
        lines = ["Drive from a browser (phone on the car's network):"]
        lines += [f"  {u.url}" + (f"  ({u.note})" if u.note else "") for u in urls]
        if self.token:
            lines.append(
                "Anyone with this link can drive"
                + ("; the token changes at every start." if isinstance(self._token_setting, _NewToken) else ".")
            )
        out.write("\n".join(lines) + "\n")
        show_qr = self.qr if self.qr is not None else bool(getattr(out, "isatty", lambda: False)())
        if show_qr:
            import segno

            segno.make(urls[0].url, error="L").terminal(out=out, compact=True)
        out.flush()


def _check_origin(request: web.Request) -> None:
    if not origin_allowed(request):
        raise web.HTTPForbidden(text=f"asyncdonkey: requests from {request.headers.get('Origin')} are not accepted\n")


def _name(client: object) -> str:
    if client is None:
        return "a script without a session"
    return client if isinstance(client, str) else f"a page ({id(client):x})"


def _text(msg: Any, intake: Intake) -> str:
    """A WebSocket message's text; a binary one is a refused value (Donkeycar's messages are JSON text)."""
    if msg.type is WSMsgType.TEXT:
        return str(msg.data)
    if msg.type is WSMsgType.ERROR:  # a frame over the socket's limit, a protocol error: the socket closes
        raise intake.refuse(COMMAND, "protocol", str(msg.data)[:80])
    raise intake.refuse(COMMAND, "type", f"a {msg.type.name.lower()} message (expected JSON text)")


async def _send_json(ws: web.WebSocketResponse, payload: dict[str, Any]) -> None:
    if ws.closed:
        return
    with contextlib.suppress(ConnectionError, RuntimeError):
        await ws.send_json(payload)


@web.middleware
async def _security_headers(request: web.Request, handler: Callable[[web.Request], Any]) -> web.StreamResponse:
    resp = await handler(request)
    if resp.content_type == "text/html":
        resp.headers.setdefault("Content-Security-Policy", _CSP)
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
    return resp
