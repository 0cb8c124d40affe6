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
import dataclasses
import functools
import logging
import threading
from collections import deque
from collections.abc import Callable
from importlib import resources
from typing import Any, Final, TextIO

from aiohttp import WSMsgType, web

from ...clock import Clock, get_clock
from ...contracts import Contracts, Gate
from ...periodic import Periodic
from ...ratelimit import LogThrottle
from .addresses import DriveUrl, InterfaceTable
from .announce import Announcer
from .auth import Access, Sessions, WebConfigError, new_token, origin_allowed
from .calibrate import (
    CALIBRATION,
    CalibrationError,
    CalibrationRecords,
    admit_config,
    apply_calibration,
    current_calibration,
    why_not_stopped,
)
from .config import NEW_TOKEN, WEB_SETTINGS, NewToken, WebConfig
from .controls import Controls
from .desk import Command, CommandError, Desk
from .guard import ConnectionGuard
from .health import vehicle_health
from .intake import COMMAND, MAX_MESSAGE_BYTES, Intake
from .pages import Pages, send_json
from .video import FrameHub

__all__ = ["NEW_TOKEN", "WEB_INPUTS", "WEB_OUTPUTS", "WebConfig", "WebController"]

logger = logging.getLogger(__name__)

WEB_INPUTS: Final = ("cam/image_array", "tub/num_records", "user/mode", "recording")
WEB_OUTPUTS: Final = ("user/angle", "user/throttle", "user/mode", "recording", "web/buttons")

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


@functools.cache
def _load_static() -> dict[str, tuple[bytes, str]]:
    """The page's files, read once from the package (a car has no internet: nothing comes from a CDN)."""
    out: dict[str, tuple[bytes, str]] = {}
    for entry in resources.files(__package__).joinpath("static").iterdir():
        suffix = "." + entry.name.rsplit(".", 1)[-1]
        if entry.is_file() and suffix in _STATIC_TYPES:
            out[entry.name] = (entry.read_bytes(), _STATIC_TYPES[suffix])
    return out


def _config(config: WebConfig | int | None, mode: str | None, settings: dict[str, Any]) -> WebConfig:
    """The controller's config: ``config`` with the keyword ``settings`` applied over it (a port and mode given
    positionally, as Donkeycar's ``LocalWebController(port, mode)`` takes them, are settings too)."""
    unknown = sorted(set(settings) - WEB_SETTINGS)
    if unknown:
        raise TypeError(
            f"WebController: unknown setting {unknown[0]!r}; "
            f"the settings are WebConfig's: {', '.join(sorted(WEB_SETTINGS))}"
        )
    if not isinstance(config, WebConfig | None):
        settings["port"] = config  # WebController(8887, ...): checked by WebConfig like any port
        config = None
    if mode is not None:
        settings["mode"] = mode
    if config is None:
        return WebConfig(**settings)
    return dataclasses.replace(config, **settings) if settings else config


class Serving:
    """What is in force while the server runs: the token, the port it listens on, its URL, and how it stops."""

    __slots__ = ("access", "listening", "port", "served", "sessions", "stop", "token", "url")

    def __init__(self, config: WebConfig) -> None:
        self.port = config.port  # the port listened on once listening (``port=0`` picks one)
        self.token: str | None = None  # the token in force (set when the server starts)
        self.url: str | None = None  # the drive URL with the token, once listening
        #: set (from the loop) once the server listens; threads may wait on it
        self.listening = threading.Event()
        self.stop: asyncio.Event | None = None
        self.served: asyncio.Future[None] | None = None
        self.access: Access | None = None
        self.sessions = Sessions(config.port, secure=config.ssl_context is not None)


class WebController:
    """A browser as the car's controller (see the module docstring and ``docs/web.md``).

    Its settings are a :class:`~.config.WebConfig`, kept apart from the controller's state: the config is the one
    place that lists what is settable, with defaults and checks (every setting is validated once, when the config
    is made, with a one-line error naming it), and, frozen, it can be shared between cars and tests and varied
    with :func:`dataclasses.replace`. ``WebController(config)`` takes one; the keyword form, as Donkeycar's
    ``LocalWebController`` is called (``WebController(8887, "user", max_throttle=0.5)``), builds one, and keywords
    given with a config are applied over it.

    The state is split by job: :class:`~.controls.Controls` (what the part outputs), :class:`~.desk.Desk` (who
    drives), :class:`~.pages.Pages` (the open pages and pushes), :class:`~.guard.ConnectionGuard` (connection
    limits and counters), :class:`~.video.FrameHub` (the video), :class:`~.announce.Announcer` (the start-up
    message), :class:`Serving` (the running server) and :class:`~.calibrate.CalibrationRecords`.

    Args:
        config: the settings (:class:`~.config.WebConfig`), or the port as Donkeycar passes it first.
        mode: the drive mode at start, as Donkeycar passes it second.
        vehicle: the Vehicle, for the page's health strip (its profiler); or give ``status``.
        status: a callable returning a JSON-able dict shown as the health strip (overrides ``vehicle``).
        steering, throttle: the ``PWMSteering`` / ``PWMThrottle`` parts ``/calibrate`` adjusts.
        settings: any of :class:`~.config.WebConfig`'s settings, applied over ``config``.
    """

    def __init__(
        self,
        config: WebConfig | int | None = None,
        mode: str | None = None,
        *,
        vehicle: Any = None,
        status: Callable[[], dict[str, Any]] | None = None,
        steering: Any = None,
        throttle: Any = None,
        **settings: Any,
    ) -> None:
        cfg = self.config = _config(config, mode, settings)
        self.steering = steering
        self.throttle_part = throttle
        self._status = status if status is not None else (lambda: vehicle_health(vehicle)) if vehicle else None
        self.outputs: list[str] = list(WEB_OUTPUTS)
        self.inputs: list[str] = list(WEB_INPUTS)
        self.controls = Controls(cfg.mode)
        self.desk = Desk(cfg.idle_release_s)
        self.pages = Pages(self.desk)
        #: connection admission: header deadline, cap, descriptor reserve (counters in ``/status``)
        self.guard = ConnectionGuard(cfg.header_timeout_s, cfg.max_connections, cfg.reserve_fds)
        self.hub = FrameHub(cfg.jpeg_quality)
        self.announcer = Announcer(cfg.announce, cfg.qr)
        self.serving = Serving(cfg)
        #: the latest calibration requests, accepted or refused (:attr:`calibrations`)
        self.calibration_records = CalibrationRecords()
        self.bad_commands = 0  # messages refused (a bad value, not JSON, too large, ...)
        self.gate: Gate
        self.intake: Intake
        self.use_contracts(Contracts())  # until Vehicle.add gives the car's own
        self.last_health: dict[str, Any] | None = None
        self._clock: Clock | None = None
        self._log = LogThrottle(5.0)

    # ================================================================================== state, by name
    @property
    def host(self) -> str:
        return self.config.host

    @property
    def port(self) -> int:
        """The port: the one listened on once the server listens (``port=0`` picks a free one)."""
        return self.serving.port

    @property
    def token(self) -> str | None:
        """The token in force, set when the server starts (``None``: no token)."""
        return self.serving.token

    @token.setter
    def token(self, value: str | None) -> None:
        self.serving.token = value

    @property
    def url(self) -> str | None:
        """The drive URL with the token, once listening."""
        return self.serving.url

    @property
    def listening(self) -> threading.Event:
        """Set (from the loop) once the server listens; threads may wait on it."""
        return self.serving.listening

    @property
    def modes(self) -> tuple[str, ...]:
        return tuple(self.config.modes)

    @property
    def max_throttle(self) -> float:
        return self.config.max_throttle

    @property
    def announce(self) -> TextIO | None:
        """Where the drive URL is printed at start (settable until then; ``None``: only logged)."""
        return self.announcer.out

    @announce.setter
    def announce(self, out: TextIO | None) -> None:
        self.announcer.out = out

    @property
    def interfaces(self) -> InterfaceTable:
        """Lists the interfaces whose addresses are printed (tests give a fake table)."""
        return self.announcer.interfaces

    @interfaces.setter
    def interfaces(self, table: InterfaceTable) -> None:
        self.announcer.interfaces = table

    @property
    def angle(self) -> float:
        return self.controls.angle

    @property
    def throttle(self) -> float:
        """The throttle command output (the throttle *part* is :attr:`throttle_part`)."""
        return self.controls.throttle

    @property
    def mode(self) -> str:
        return self.controls.mode

    @property
    def recording(self) -> bool:
        return self.controls.recording

    @property
    def num_records(self) -> int:
        return self.controls.num_records

    @property
    def commands(self) -> int:
        """Drive commands applied."""
        return self.controls.commands

    @property
    def ticks(self) -> int:
        return self.controls.ticks

    @property
    def calibrations(self) -> deque[dict[str, Any]]:
        """The latest calibration requests, accepted or refused: when, who, what was asked, what changed, why not."""
        return self.calibration_records.records

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
        if self.desk.driver is not None and self.desk.expire(self._now()):
            self._on_release("went quiet")
        changes, buttons = self.controls.tick(mode, recording, num_records)
        if changes:
            self.pages.broadcast(changes)
        return self.controls.outputs(buttons)

    run_threaded = run

    def output_origin(self) -> float | None:
        """Arrival time of the driver's latest command (server start before any): what ``@age`` measures."""
        return self.controls.origin

    async def update(self) -> None:
        """Serve until :meth:`shutdown` (a background task beside the ticks)."""
        loop = self.pages.loop = asyncio.get_running_loop()
        clock = self._clock = get_clock(loop)
        serving = self.serving
        serving.stop = asyncio.Event()
        serving.served = loop.create_future()
        token = self.config.token
        serving.token = new_token() if isinstance(token, NewToken) else token
        runner = web.AppRunner(self._make_app(), access_log=None, shutdown_timeout=1.0, keepalive_timeout=_KEEPALIVE_S)
        try:
            await runner.setup()
            serving.port = await self._listen(runner)
            assert serving.access is not None
            serving.access.cookie = f"asyncdonkey-token-{serving.port}"
            serving.sessions.cookie = f"asyncdonkey-session-{serving.port}"
            self.controls.origin = clock.now()
            urls = await loop.run_in_executor(None, self._urls)  # lists the interfaces (a netlink round trip)
            serving.url = urls[0].url
            self._announce(urls)
            serving.listening.set()
            tasks = [
                asyncio.create_task(self.hub.run(), name="web video encoder"),
                asyncio.create_task(self._health_loop(), name="web health"),
            ]
            try:
                await serving.stop.wait()
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
        finally:
            await self._close(runner)
            serving.listening.clear()
            if not serving.served.done():
                serving.served.set_result(None)

    async def shutdown(self, timeout: float = 2.0) -> None:
        """Close every connection and stop listening (waits up to ``timeout`` seconds)."""
        stop, served = self.serving.stop, self.serving.served
        if stop is None or served is None:
            return
        stop.set()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(served), timeout)

    async def _listen(self, runner: web.AppRunner) -> int:
        """Listen, the connection guard accepting (TLS too: the guard hands the socket over for the handshake,
        so a connection that never completes one is seen, counted and timed out like any other). Returns the
        port."""
        assert runner.server is not None
        cfg = self.config
        try:
            bound = await self.guard.start(
                runner.server, cfg.host, self.port, backlog=cfg.backlog, ssl_context=cfg.ssl_context
            )
        except OSError as exc:
            raise WebConfigError(f"WebController: cannot listen on {cfg.host}:{self.port}: {exc}") from exc
        return int(bound[0][1])

    async def _close(self, runner: web.AppRunner) -> None:
        await self.guard.stop()  # no new connections; aiohttp's cleanup below closes the open ones
        await self.hub.close()
        await self.pages.close()
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
            self.controls.stop(now)  # throttle 0, and the pilot loses the car too
            logger.warning("web: stop from %s", self.pages.describe(client))
        if cmd.release and client is not None and self.desk.release(client):
            self._on_release("released")
        if cmd.drives:
            if not self._may_drive(client, now):
                return "other"
            self.controls.drive(cmd, self.config.max_throttle, now)
        if self.desk.driver is not before:
            self.pages.push_roles(now)
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
        self.controls.neutral()
        logger.info("web: the driver %s; control is free", why)
        self.pages.push_roles(self._now())

    # ================================================================================== server
    def _make_app(self) -> web.Application:
        access = self.serving.access = Access(self.token, self.port, on_admit=self.guard.admit)
        # a body over the message limit is refused when read (never buffered whole): see _read_body
        app = web.Application(middlewares=[access.middleware, _security_headers], client_max_size=MAX_MESSAGE_BYTES)
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
            body, ctype = _load_static()[name]
            return web.Response(body=body, content_type=ctype, headers={"Cache-Control": "no-cache"})

        return handler

    async def _get_static(self, request: web.Request) -> web.StreamResponse:
        found = _load_static().get(request.match_info["name"])
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
            "command_age_s": (now - origin) if (origin := self.controls.origin) is not None else None,
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
        session = self.serving.sessions.of(request)
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
            self.serving.sessions.issue(resp)  # a client that keeps it can hold control from its next command
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
        self.pages.opened(ws, request)
        role = self.pages.roles[ws] = self.desk.role(ws, self._now())
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
            if self.pages.closed(ws):
                self._on_release("closed the page")
        return ws

    def _on_message(self, ws: web.WebSocketResponse, msg: Any) -> None:
        """One message from a drive page: applied, or refused with an ``error`` push; the socket stays open
        whatever it carried (a dropped driver's socket would release control: one bad value must not)."""
        try:
            role = self.apply(ws, self.intake.command(self.intake.decode(_text(msg, self.intake))))
        except CommandError as exc:
            self.bad_commands += 1
            self.pages.send(ws, {"error": str(exc)})
            return
        except Exception as exc:  # a bug here must not drop the driver: say so loudly, keep the socket
            self._internal_error(ws, exc)
            return
        self.pages.tell_role(ws, role)

    def _internal_error(self, ws: web.WebSocketResponse, exc: Exception) -> None:
        self.bad_commands += 1
        held = self._log.ready("internal", self._now(), "failures")
        if held is not None:
            logger.error("web: a message could not be handled%s", held, exc_info=exc)
        self.pages.send(ws, {"error": f"web: the car could not handle that message ({type(exc).__name__})"})

    async def _ws_calibrate(self, request: web.Request) -> web.StreamResponse:
        _check_origin(request)
        ws = web.WebSocketResponse(heartbeat=2.0, max_msg_size=_WS_FRAME_LIMIT)
        await ws.prepare(request)
        self.pages.opened(ws, request)
        try:
            await ws.send_json({"config": current_calibration(self.steering, self.throttle_part)})
            async for msg in ws:
                for payload in self._on_calibrate_message(ws, msg):
                    await send_json(ws, payload)
        finally:
            if self.pages.closed(ws):
                self._on_release("closed the calibration page")
        return ws

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
        who = self.pages.describe(client)
        try:
            pulses = admit_config(self.intake, config)  # each refused value is counted by the gate as it goes
        except CalibrationError as exc:
            self.calibration_records.refused(now, who, config, exc)
            raise
        try:
            refusal = self.desk.why_not_calibrator(client, now)
            if refusal is not None:
                raise CalibrationError(f"calibration: {refusal}", reason="not_driver")
            moving = why_not_stopped(self.controls.throttle, self.controls.mode, self.throttle_part)
            if moving is not None:
                raise CalibrationError(f"calibration: the car must be stopped to calibrate: {moving}", reason="moving")
            before = current_calibration(self.steering, self.throttle_part)
            applied = apply_calibration(self.steering, self.throttle_part, pulses)
        except CalibrationError as exc:
            self.gate.refuse(exc.channel, exc.reason, str(exc), now)
            self.calibration_records.refused(now, who, pulses, exc)
            raise
        driver = self.desk.driver
        self.desk.claim(client, now)  # the calibrator holds control: a watcher's drive commands are "other"
        if self.desk.driver is not driver:
            self.pages.push_roles(now)
        changed = {k: [before[k], v] for k, v in applied.items() if before.get(k) != v}
        self.calibration_records.accepted(now, who, pulses, changed)
        return applied

    # ================================================================================== pushes
    async def _health_loop(self) -> None:
        clock = self._clock
        assert clock is not None
        last_t, last_n = clock.now(), self.ticks
        with Periodic(self.config.health_every_s) as every:
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
                self.pages.push_roles(now)
                if self.pages.roles:
                    self.pages.broadcast_now({"health": health})

    # ================================================================================== start-up message
    def _urls(self) -> list[DriveUrl]:
        """The drive URLs to print, the one for the QR code first (:mod:`.addresses`)."""
        secure = self.config.ssl_context is not None
        return self.announcer.urls(self.config.host, self.port, self.token, secure=secure)

    def _announce(self, urls: list[DriveUrl]) -> None:
        fresh = isinstance(self.config.token, NewToken)
        self.announcer.announce(self.config.host, self.port, urls, token=bool(self.token), fresh_token=fresh)


def _check_origin(request: web.Request) -> None:
    if not origin_allowed(request):
        raise web.HTTPForbidden(text=f"asyncdonkey: requests from {request.headers.get('Origin')} are not accepted\n")


def _text(msg: Any, intake: Intake) -> str:
    """A WebSocket message's text; a binary one is a refused value (Donkeycar's messages are JSON text)."""
    if msg.type is WSMsgType.TEXT:
        return str(msg.data)
    if msg.type is WSMsgType.ERROR:  # a frame over the socket's limit, a protocol error: the socket closes
        raise intake.refuse(COMMAND, "protocol", str(msg.data)[:80])
    raise intake.refuse(COMMAND, "type", f"a {msg.type.name.lower()} message (expected JSON text)")


@web.middleware
async def _security_headers(request: web.Request, handler: Callable[[web.Request], Any]) -> web.StreamResponse:
    resp = await handler(request)
    if resp.content_type == "text/html":
        resp.headers.setdefault("Content-Security-Policy", _CSP)
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
    return resp
