"""The simulated Donkey car: camera -> controller -> pilot -> drive mode -> actuators -> recording, at 20 Hz.

    make run                                                # 25 s (a lap and a bit) on the shipped pilot
    make run ARGS="-- --seconds 120"                        # longer (0: until Ctrl-C)
    make run ARGS="-- --laps 3"                             # until 3 laps (no time limit unless --seconds)
    make run ARGS="-- --pilot user --record data/tub"       # the scripted "user" drives and records
    make run ARGS="-- --pilot models/mine.onnx"             # drive on your own model (.onnx or .tflite)
    make run ARGS="-- --web"                                # drive it yourself from a browser or a phone
    asyncdonkey run examples/car.py --hz 50 -- --laps 3     # any rate; stop after 3 laps
    asyncdonkey run examples/car.py -- --pilot remote --zenoh-listen tcp/127.0.0.1:7447   # off-board pilot

The parts are the ones a real car uses, in Donkeycar's order and with Donkeycar's channel names; only the
camera and the actuators are the simulator's (see ``examples/car_pi.py`` for the same graph on hardware):

========================= =============================================== =====================================
part                      inputs                                          outputs
========================= =============================================== =====================================
SimCamera                                                                 cam/image_array
SimTelemetry                                                              sim/x, sim/y, sim/heading, ... sim/cte
SimController             sim/x, sim/y, sim/heading                       user/angle, user/throttle, user/mode,
                                                                          recording
PilotCondition            user/mode                                       run_pilot
pilot (if run_pilot)      cam/image_array                                 pilot/angle, pilot/throttle
DriveMode                 user/mode, user/*, pilot/*                      angle, throttle
SimCar                    angle, throttle
TubWriter (if recording)  cam/image_array, user/*, pilot/*, sim/cte ...   tub/num_records
Status                    sim/laps, sim/cte, sim/off_track
========================= =============================================== =====================================

The simulated controller is a scripted driver (pure pursuit with a human-like wobble) standing in for a person
with a joystick. It keeps driving "in its head" while the pilot has the car, so recordings made in pilot mode
carry the driver's command for every frame the pilot saw: the labels a DAgger round trains on.

With ``--web`` a person drives instead: the controller is the :class:`~asyncdonkey.parts.web.WebController`
(open the URL it prints), the drive runs until Ctrl-C, and the page's mode buttons hand the car to the pilot
and back. The simulated car has no ESC, so a :class:`~asyncdonkey.parts.failsafe.StaleCommandStop` does what
``PWMThrottle``'s failsafe does on a real car: a page that goes quiet, hidden or away stops the car.

With ``--pilot remote`` the pilot runs in another process or on another machine (``examples/remote_pilot.py``):
the car publishes its camera frames, telemetry and status over Zenoh under ``cars/sim`` and takes
``pilot/angle, pilot/throttle`` from the network, together as one sample (``cars/sim/pilot/command``), each
checked against its channel's contract (a bad value is refused and counted, never applied); a
:class:`StaleCommandStop` before the simulated car stops it when the remote command is ``--failsafe-ms`` old
(see ``docs/scale-out.md``).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from asyncdonkey import Vehicle, get_clock
from asyncdonkey.extras import require
from asyncdonkey.options import non_negative_float, non_negative_int, option
from asyncdonkey.parts.control import DRIVE_MODES, AutoRecordOnThrottle, DriveMode, PilotCondition, normalise_mode
from asyncdonkey.parts.sim import TELEMETRY_OUTPUTS, ScriptedDriver, SimCar, Simulator

DRIVE_LOOP_HZ = 20
#: how long `make run` drives when neither --seconds nor --laps is given (a lap and a bit)
DEFAULT_SECONDS = 25.0
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "sim_pilot.onnx"
#: Where the car's channels live on the network with ``--pilot remote``.
REMOTE_PREFIX = "cars/sim"
#: What a recording holds: Donkeycar's channels plus the simulator's ground truth for analysis.
RECORD_INPUTS = (
    ("cam/image_array", "image_array"),
    ("user/angle", "float"),
    ("user/throttle", "float"),
    ("user/mode", "str"),
    ("pilot/angle", "float"),
    ("pilot/throttle", "float"),
    ("sim/cte", "float"),
    ("sim/laps", "int"),
)


#: How the pilot runs (``--pilot-mode``).
PILOT_MODES = ("in-order", "pipelined", "frame")


class SlowedPilot:
    """A pilot whose every inference takes ``delay`` seconds longer (``--pilot-delay``): the simulated car
    driven by the pilot a Raspberry Pi would run, to see what pipelining buys."""

    def __init__(self, pilot: Any, delay: float) -> None:
        self.pilot = pilot
        self.delay = delay

    async def run(self, image: Any) -> Any:
        result = await self.pilot.run(image)
        await asyncio.sleep(self.delay)
        return result

    def shutdown(self) -> Any:
        return self.pilot.shutdown()


def recent_lateness_p99_ms(vehicle: Vehicle, ticks: int = 200) -> float | None:
    """Tick lateness p99 over the last ``ticks`` ticks, in ms (``None`` before the first tick)."""
    late = vehicle.profiler.lateness.recent(drop_last=False)[-ticks:]
    return float(np.percentile(late, 99)) * 1e3 if len(late) else None


def recent_latency_p99_ms(vehicle: Vehicle, ticks: int = 200) -> float | None:
    """Sensing-to-actuation latency p99 of the car's (first) actuator over its last ``ticks`` commands, in ms."""
    series = next(iter(vehicle.profiler.latency.values()), None)
    lat = series.recent(drop_last=False)[-ticks:] if series is not None else ()
    return float(np.percentile(lat, 99)) * 1e3 if len(lat) else None


class SimController:
    """The simulator's stand-in for a person at the controller: Donkeycar's four controller outputs.

    ``user/angle, user/throttle`` come from a :class:`ScriptedDriver`; ``user/mode`` is fixed for the drive;
    ``recording`` follows :class:`AutoRecordOnThrottle` in ``user`` mode and is on for every frame in the
    pilot modes (when recording was asked for at all).
    """

    def __init__(self, driver: ScriptedDriver, mode: str, record: bool) -> None:
        self.driver = driver
        self.mode = normalise_mode(mode, "SimController")
        self.record = record
        self.auto_record = AutoRecordOnThrottle(dead_zone=0.01)

    def run(self, x: Any, y: Any, heading: Any) -> tuple[float, float, str, bool]:
        angle, throttle = self.driver.run(x, y, heading)
        if not self.record:
            recording = False
        elif self.mode == "user":
            recording = self.auto_record.run(self.mode, throttle)
        else:
            recording = True
        return angle, throttle, self.mode, recording


class Status:
    """A live one-line status (laps, achieved Hz, tick lateness p99, cross-track error) and the stop rule.

    ``run`` takes the tick's telemetry and asks the vehicle to stop after ``seconds`` of runtime clock or
    ``laps`` laps, with that reason (the drive report's "stopped by"). ``update`` is a background task that
    redraws the line every ``every`` seconds: in place on a terminal, as separate lines (every few seconds) in
    a log. ``live=False`` (``--quiet``) leaves the line out; the summary of the drive is still written at the
    end, as it is the drive's result.
    """

    def __init__(
        self,
        vehicle: Vehicle,
        car: SimCar,
        *,
        seconds: float = 20.0,
        laps: int = 0,
        stream: TextIO | None = sys.stderr,
        every: float = 0.5,
        live: bool = True,
    ) -> None:
        self.vehicle = vehicle
        self.live = live
        self.car = car
        self.seconds = seconds
        self.laps_target = laps
        self.stream = stream
        self.tty = bool(stream is not None and getattr(stream, "isatty", lambda: False)())
        self.every = every if self.tty else max(every, 5.0)
        self.laps = 0
        self.cte = 0.0
        self.abs_cte_sum = 0.0
        self.abs_cte_max = 0.0
        self.off_track_ticks = 0
        self.ticks = 0
        self._t0: float | None = None
        self._t_last = 0.0
        self._line_open = False

    def run(self, laps: Any, cte: Any, off_track: Any) -> None:
        now = get_clock().now()
        if self._t0 is None:
            self._t0 = now
        self._t_last = now
        self.ticks += 1
        self.laps = int(laps or 0)
        self.cte = float(cte or 0.0)
        self.abs_cte_sum += abs(self.cte)
        self.abs_cte_max = max(self.abs_cte_max, abs(self.cte))
        self.off_track_ticks += bool(off_track)
        if self.seconds > 0 and now - self._t0 >= self.seconds:
            self.vehicle.stop(f"time limit reached ({self.seconds:g} s)")
        elif 0 < self.laps_target <= self.laps:
            self.vehicle.stop(f"lap target reached ({self.laps_target} lap{'' if self.laps_target == 1 else 's'})")

    def line(self, hz: float) -> str:
        p99 = recent_lateness_p99_ms(self.vehicle) or 0.0
        latency = recent_latency_p99_ms(self.vehicle) or 0.0
        mean_cte = self.abs_cte_sum / self.ticks if self.ticks else 0.0
        lap_share = (self.car.sim.progress / self.car.sim.track.length) % 1.0
        return (
            f"laps {self.laps:3d} (+{lap_share:4.0%}) | {hz:5.1f} Hz | lateness p99 {p99:6.2f} ms | "
            f"sensing→actuation p99 {latency:5.1f} ms | "
            f"cte {self.cte:+.2f} m (mean |cte| {mean_cte:.2f}) | off track {self.off_track_ticks} ticks | "
            f"respawns {self.car.sim.respawns}"
        )

    async def update(self) -> None:
        clock = get_clock()
        last_t, last_n = clock.now(), self.ticks
        k = 1
        t0 = last_t
        while True:
            await clock.sleep_until(t0 + k * self.every)
            k += 1
            now, n = clock.now(), self.ticks
            hz = (n - last_n) / (now - last_t) if now > last_t else 0.0
            last_t, last_n = now, n
            self._write(self.line(hz))

    def _write(self, text: str) -> None:
        if self.stream is None or not self.live:
            return
        if self.tty:
            self.stream.write("\r\x1b[2K" + text)
            self._line_open = True
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def summary(self) -> str:
        """The drive in one line, printed when the car stops."""
        seconds = (self._t_last - self._t0) if self._t0 is not None else 0.0
        mean_cte = self.abs_cte_sum / self.ticks if self.ticks else 0.0
        return (
            f"drove {self.laps} lap{'' if self.laps == 1 else 's'} ({self.car.sim.progress:.0f} m) in {seconds:.1f} s: "
            f"mean |cte| {mean_cte:.3f} m, max {self.abs_cte_max:.3f} m, off track {self.off_track_ticks} ticks, "
            f"respawns {self.car.sim.respawns}"
        )

    def shutdown(self) -> None:
        if self.stream is None or not self.ticks:  # a car that never drove (it refused to start) has no summary
            return
        if self._line_open:
            self.stream.write("\n")
            self._line_open = False
        self.stream.write(self.summary() + "\n")
        self.stream.flush()


def make_car(
    *,
    pilot: str | Path = DEFAULT_MODEL,
    mode: str | None = None,
    record: str | Path | None = None,
    mcap: str | Path | None = None,
    seconds: float = DEFAULT_SECONDS,
    laps: int = 0,
    ai_throttle_mult: float = 1.3,
    seed: int = 0,
    status: TextIO | None = sys.stderr,
    live_status: bool = True,
    rate_hz: float = DRIVE_LOOP_HZ,
    pilot_mode: str = "frame",
    pilot_delay: float = 0.0,
    web: dict[str, Any] | None = None,
    zenoh: Any = None,
    prefix: str = REMOTE_PREFIX,
    jpeg: int | None = None,
    failsafe_s: float = 0.25,
    insecure: bool = False,
) -> tuple[Vehicle, SimCar]:
    """Assemble the simulated car. ``pilot`` is a model path (``.onnx`` or ``.tflite``), ``"user"`` (no pilot) or
    ``"remote"``.

    ``"remote"``: the pilot's commands come over Zenoh (``zenoh`` is the session config or config file) under
    ``prefix``; the camera goes out raw, or as JPEG of quality ``jpeg``. ``insecure``: take the commands even
    from a session others can publish to (an isolated bench network only).

    ``pilot_mode``: ``"in-order"`` (the pilot inside the tick, as Donkeycar runs it), ``"pipelined"`` (beside
    the ticks, started each tick) or ``"frame"`` (beside the ticks, started by each new camera frame, with the
    drive mode and the car reacting at once to its commands). ``pilot_delay`` adds that many seconds to each
    inference, to drive with the pilot a Raspberry Pi would run (``--pilot-delay 0.08``). ``web``: drive from a
    browser; the dict holds :class:`~asyncdonkey.parts.web.WebController` arguments (``{}`` for the defaults).

    ``status`` is where the live status line and the drive's summary go (``None``: nowhere); ``live_status=False``
    writes the summary alone.

    Returns the vehicle and the simulated car (for its simulator's state after the drive).
    """
    user_only = str(pilot) == "user"
    remote = str(pilot) == "remote"
    drive_mode = normalise_mode(mode or ("user" if user_only or web is not None else "local"), "car.py --mode")
    if user_only and drive_mode != "user":
        raise ValueError(f"--mode {drive_mode} needs a pilot; --pilot user drives in user mode only")

    v = Vehicle()
    car = SimCar(Simulator(respawn_after_s=1.0))
    car.sim.render()  # builds the track texture and camera tables now, not in the first tick
    v.add(car.camera, outputs=["cam/image_array"])
    v.add(car.telemetry, outputs=list(TELEMETRY_OUTPUTS))
    if remote:
        require("zenoh", "zenoh", "--pilot remote (a pilot over Zenoh)")
        from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohLink, ZenohPublisher, ZenohSubscriber

        link = ZenohLink(prefix, zenoh, insecure=insecure)
        frames_at_capture = pilot_mode == "frame"
        camera_out = ZenohPublisher(
            link,
            ["cam/image_array"],
            jpeg={"cam/image_array": jpeg} if jpeg else None,
            on_change=frames_at_capture,  # the tick then skips the frame already sent when it was captured
        )
        # frame mode: each frame goes out the moment the simulated camera renders it, not at the next tick
        v.add(camera_out, inputs=camera_out.inputs, react=frames_at_capture)
    if web is not None:
        from asyncdonkey.parts.web import WebController

        controller = WebController(mode=drive_mode, vehicle=v, **web)
        v.add(controller, inputs=controller.inputs, outputs=controller.outputs, name="web")
    else:
        driver = ScriptedDriver(car.sim.track, seed=seed, rate_hz=rate_hz)
        v.add(
            SimController(driver, drive_mode, record is not None),
            inputs=["sim/x", "sim/y", "sim/heading"],
            outputs=["user/angle", "user/throttle", "user/mode", "recording"],
        )
    if pilot_mode not in PILOT_MODES:
        raise ValueError(f"car.py --pilot-mode: expected one of {', '.join(PILOT_MODES)}, got {pilot_mode!r}")
    # frame mode: the drive mode and the car take each command the moment it exists (from the pipelined pilot,
    # or as it arrives from the network for a remote pilot), not at the next tick
    react = not user_only and pilot_mode == "frame"
    if remote:  # angle and throttle in one sample: applied together, with one origin
        commands = ZenohSubscriber(link, ["pilot/angle", "pilot/throttle"], group=PILOT_COMMAND)
        v.add(commands, outputs=["pilot/angle", "pilot/throttle"])
    elif not user_only:
        from asyncdonkey.parts.pilot import load_pilot  # the runtime loads only when a pilot drives

        v.add(PilotCondition(), inputs=["user/mode"], outputs=["run_pilot"])
        model: Any = load_pilot(pilot)
        v.add(
            SlowedPilot(model, pilot_delay) if pilot_delay > 0 else model,
            inputs=["cam/image_array"],
            outputs=["pilot/angle", "pilot/throttle"],
            run_condition="run_pilot",
            pipelined=pilot_mode != "in-order",
            trigger="cam/image_array" if pilot_mode == "frame" else None,
            name=type(model).__name__,
        )
    v.add(
        DriveMode(ai_throttle_mult=ai_throttle_mult),
        inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
        outputs=["angle", "throttle"],
        react=react,
    )
    if web is not None or remote:
        # a person on a web page or a pilot on the network: the simulated car has no ESC, so the library's
        # stale-command stop does what PWMThrottle's failsafe does on a real car
        from asyncdonkey.parts.failsafe import StaleCommandStop

        limit = failsafe_s if remote else 0.25
        v.add(StaleCommandStop(limit), inputs=["throttle", "throttle@age"], outputs=["sim/throttle"], react=react)
        v.add(car, inputs=["angle", "sim/throttle"], react=react)
    else:
        v.add(car, inputs=["angle", "throttle"], react=react)
    if record is not None:
        from asyncdonkey.parts.tub import TubWriter

        names, types = zip(*RECORD_INPUTS, strict=True)
        writer = TubWriter(record, inputs=names, types=types, metadata=[f"pilot:{pilot}", f"mode:{drive_mode}"])
        v.add(writer, inputs=list(names), outputs=["tub/num_records"], run_condition="recording")
    if remote:
        from asyncdonkey.parts.zenoh.fleet import FleetStatus

        telemetry_out = ZenohPublisher(link, ["sim/throttle", "angle", "sim/speed", "sim/cte", "sim/laps"])
        v.add(telemetry_out, inputs=telemetry_out.inputs)
        fleet = FleetStatus(link, v, ages=["cam/image_array", "pilot/throttle", "sim/throttle"])
        v.add(fleet, inputs=["user/mode", "tub/num_records"])
    v.add(
        Status(v, car, seconds=seconds, laps=laps, stream=status, live=live_status),
        inputs=["sim/laps", "sim/cte", "sim/off_track"],
    )
    if mcap is not None:  # the whole drive (every channel, the loop's timing) for Foxglove and `report`
        from asyncdonkey.parts.mcap import McapRecorder

        v.add(McapRecorder(mcap, v, metadata={"pilot": pilot, "mode": drive_mode}), name="McapRecorder")
    return v, car


def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="asyncdonkey run examples/car.py --", description="the simulated car")
    ap.add_argument(
        "--pilot",
        default=str(DEFAULT_MODEL),
        help="model to drive on (.onnx, or .tflite with the tflite extra), 'user' for the scripted driver alone, "
        "or 'remote' for a pilot over Zenoh (default: the shipped sim pilot)",
    )
    ap.add_argument("--mode", choices=DRIVE_MODES, help="drive mode (default: local with a pilot)")
    ap.add_argument("--record", metavar="TUB", help="record a Tub v2 into this directory")
    ap.add_argument("--mcap", metavar="FILE", help="record the whole drive to this MCAP file (asyncdonkey[mcap])")
    ap.add_argument(
        "--seconds",
        type=option(non_negative_float),
        default=None,
        help=f"stop after S seconds (0: no time limit; default {DEFAULT_SECONDS:g}, or no limit with --laps or --web)",
    )
    ap.add_argument(
        "--laps", type=option(non_negative_int), default=0, help="stop after N laps (0: no limit; the default)"
    )
    ap.add_argument(
        "--ai-throttle-mult",
        type=option(non_negative_float),
        default=1.3,
        help="scale the pilot's throttle (default 1.3: the shipped pilot learnt the scripted driver's cautious pace)",
    )
    ap.add_argument("--seed", type=option(non_negative_int), default=0, help="the scripted driver's seed")
    ap.add_argument(
        "--pilot-mode",
        choices=PILOT_MODES,
        default="frame",
        help="how the pilot runs: in-order (inside the tick, as Donkeycar), pipelined (beside the ticks), frame "
        "(beside the ticks, started by each camera frame, its commands applied at once; the default: the lowest "
        "sensing-to-actuation latency, docs/control-periods.md)",
    )
    ap.add_argument(
        "--pilot-delay",
        type=option(non_negative_float),
        default=0.0,
        help="add S seconds to each inference (0.08: a Raspberry Pi 4's float32 pilot)",
    )
    ap.add_argument(
        "--quiet", action="store_true", help="no live status line (the drive's summary is still printed at the end)"
    )
    ap.add_argument("--web", action="store_true", help="drive from a browser: the web controller replaces the script")
    ap.add_argument("--web-port", type=option(non_negative_int), default=8887, help="the web controller's port")
    ap.add_argument(
        "--web-host", default="0.0.0.0", help="address to listen on (default: all, so a phone on the LAN can drive)"
    )
    net = ap.add_argument_group("remote pilot (--pilot remote)")
    net.add_argument("--zenoh-config", metavar="FILE", help="Zenoh config file (e.g. car.json5 from zenoh-pair)")
    net.add_argument(
        "--zenoh-listen", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447 on a bench"
    )
    net.add_argument(
        "--zenoh-connect", action="append", default=[], metavar="ENDPOINT", help="a Zenoh endpoint to connect to"
    )
    net.add_argument(
        "--prefix", default=REMOTE_PREFIX, help=f"key prefix of the car's channels (default {REMOTE_PREFIX})"
    )
    net.add_argument("--jpeg", type=int, metavar="QUALITY", help="send camera frames as JPEG of this quality")
    net.add_argument("--failsafe-ms", type=float, default=250, help="stop when the command is this old (default 250)")
    net.add_argument(
        "--zenoh-insecure",
        action="store_true",
        help="take commands even from a session others can publish to (plain TCP beyond loopback, no access "
        "rules): an isolated bench network only",
    )
    args = ap.parse_args(argv)
    if args.seconds is None:  # --laps N or --web drive without a time limit; otherwise DEFAULT_SECONDS
        args.seconds = 0.0 if args.laps or args.web else DEFAULT_SECONDS
    return args


def build(argv: list[str]) -> Vehicle:
    """The ``asyncdonkey run`` entry: options after ``--`` (see ``--help``)."""
    args = parse_args(argv)
    zenoh = None
    if args.pilot == "remote":
        require("zenoh", "zenoh", "--pilot remote (a pilot over Zenoh)")
        from asyncdonkey.parts.zenoh import zenoh_config

        if not (args.zenoh_config or args.zenoh_listen or args.zenoh_connect):
            raise ValueError(
                "--pilot remote needs --zenoh-config FILE (the car config of `asyncdonkey zenoh-pair`) or, on a bench,"
                " --zenoh-listen tcp/127.0.0.1:PORT: Zenoh's defaults would let anyone on the network steer the car"
            )
        zenoh = zenoh_config(
            args.zenoh_config,
            mode="peer" if args.zenoh_listen or args.zenoh_connect else None,
            listen=args.zenoh_listen,
            connect=args.zenoh_connect,
            multicast_scouting=False if args.zenoh_listen or args.zenoh_connect else None,
        )
    elif args.pilot != "user" and not Path(args.pilot).is_file():
        hint = " (make it with: python examples/train.py)" if Path(args.pilot) == DEFAULT_MODEL else ""
        raise FileNotFoundError(f"pilot model {args.pilot} not found{hint}; or drive with --pilot user")
    vehicle, _ = make_car(
        pilot=args.pilot,
        mode=args.mode,
        record=args.record,
        mcap=args.mcap,
        seconds=args.seconds,
        laps=args.laps,
        ai_throttle_mult=args.ai_throttle_mult,
        seed=args.seed,
        status=sys.stderr,
        live_status=not args.quiet,
        pilot_mode=args.pilot_mode,
        pilot_delay=args.pilot_delay,
        web={"port": args.web_port, "host": args.web_host} if args.web else None,
        zenoh=zenoh,
        prefix=args.prefix,
        jpeg=args.jpeg,
        failsafe_s=args.failsafe_ms / 1e3,
        insecure=args.zenoh_insecure,
    )
    return vehicle
