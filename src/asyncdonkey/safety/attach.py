"""The safety attachment of one drive: its safety process, its watchdog, and each actuator wired to them.

The drive (:class:`~asyncdonkey.core.drive.Drive`) calls these three steps of its lifecycle:
:func:`start_safety_process` before its background work starts, :func:`attach_actuators` right after, and
:func:`detach_actuators` once shutdown has run, whatever ended the drive. They sit here, beside the watchdog and
the safety process they start, so that everything that guards the actuators is in one package; they see the drive
only through
:class:`SafetyHost` (its runs, clock, channels and stop request), never through the
``Drive`` class, and they import no part: an actuator says what it is through its own attributes
(``safety_route()``, ``failsafe_age_s``, ``stops_motion``, ``attach()``).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Protocol

from .activity import LoopActivity
from .process import GuardedOutput, SafetyProcess, SafetyProcessError, heartbeat_timeout_for
from .watchdog import ActuatorRuntime, Watchdog, watched

if TYPE_CHECKING:  # types only: the core imports this module
    from ..clock import Clock
    from ..core.partrun import PartRun
    from ..core.plan import Entry
    from ..memory import Memory

__all__ = ["Recorder", "SafetyHost", "attach_actuators", "detach_actuators", "start_safety_process"]

logger = logging.getLogger("asyncdonkey.loop")

#: ``record(t, origin)``: the command sensed at ``origin`` reached the actuator's output at ``t``
Recorder = Callable[[float, float], None]


class SafetyHost(LoopActivity, Protocol):
    """A drive as its safety attachment (``asyncdonkey.safety.attach``) sees it: the parts' runs, the clock, the
    channels' origins, the stop request the safety process may make, and the watchdog and safety process it
    attaches (and the drive reports on)."""

    @property
    def runs(self) -> Sequence[PartRun]: ...

    @property
    def clock(self) -> Clock: ...

    @property
    def mem(self) -> Memory: ...

    #: set by the attachment: the in-process watchdog (``None``: none runs)
    watchdog: Watchdog | None
    #: set by the attachment: the safety process (``None``: none runs)
    safety_process: SafetyProcess | None

    def request_stop(self, reason: str = ...) -> None: ...


async def start_safety_process(
    drive: SafetyHost, rate_hz: float, want: bool | None, exit_grace_s: float | None
) -> SafetyProcess | None:
    """Start the safety process for the actuators it can reach, as ``want`` asks (``Vehicle.safety_process``:
    ``None`` starts it when it can and drives on without it, logging why, if it cannot; ``True`` requires it;
    ``False`` never starts it). ``exit_grace_s`` is the exit grace it enforces while the car's signal handlers are
    installed (``None``: they are not).

    Never on the virtual clock: there, time stands still while the loop thread is busy, so nothing can go
    stale behind its back, and a real process beside virtual time would see every deadline as long past."""
    if want is False or drive.clock.is_virtual:
        return None
    outputs: list[GuardedOutput] = []
    windows: list[float | None] = []
    for e in drive.entries:
        routed = getattr(e.part, "safety_route", None) if e.actuator else None
        route = routed() if callable(routed) else None
        if route is not None:
            stops_motion = getattr(e.part, "stops_motion", False) is True
            outputs.append(GuardedOutput(e.name, route, e.part, stops_motion=stops_motion))
            windows.append(getattr(e.part, "failsafe_age_s", None))
    if not outputs:
        if want:
            raise SafetyProcessError(
                "Vehicle(safety_process=True): no actuator has an output another process can reach (a PCA9685 "
                "channel given by pin spec or PWMChannel)"
            )
        return None
    guard = SafetyProcess(outputs, heartbeat_timeout_for(windows, rate_hz), exit_grace_s)
    try:
        await asyncio.get_running_loop().run_in_executor(None, guard.start)
    except (SafetyProcessError, OSError) as exc:
        guard.kill()
        if want:
            raise SafetyProcessError(str(exc)) from exc
        logger.error("%s; driving with the in-process watchdog only", exc)
        return None
    if exit_grace_s is not None:
        guard.watch_signals()  # the car's signal handlers are installed: the guard hears the signals too
    guard.stop_drive = drive.request_stop
    return guard


def attach_actuators(drive: SafetyHost, recorders: Mapping[str, Recorder]) -> None:
    """Give each actuator its latency recorder (``recorders``, by part name: on the part through ``attach()``, or
    on its run for this drive), and start the watchdog on a real loop."""
    actuators = [r for r in drive.runs if r.entry.actuator]
    if not actuators:
        return
    guarded = watched(r.entry for r in actuators)
    if guarded and not drive.clock.is_virtual:
        drive.watchdog = Watchdog(drive, guarded, drive.clock.now)
    safety = drive.safety_process
    slot = {o.name: i for i, o in enumerate(safety.outputs)} if safety is not None else {}
    for r in actuators:
        e = r.entry
        record = recorders[e.name]
        attach = getattr(e.part, "attach", None)
        if callable(attach):
            i = slot.get(e.name)
            if safety is not None and i is not None:
                attach(ActuatorRuntime(record, drive.watchdog, safety.deadline_setter(i), _last_event(safety, i)))
            else:
                attach(ActuatorRuntime(record, drive.watchdog))
        else:
            r.latency = _run_end_latency(record, drive.mem.origins, e)
    if drive.watchdog is not None:
        if safety is not None:
            drive.watchdog.monitor = safety.check  # the car watches its guard from the watchdog thread
        drive.watchdog.start()


def detach_actuators(drive: SafetyHost) -> None:
    """Stop the watchdog and the safety process, and take each actuator's runtime back (``attach(None)``)."""
    if drive.watchdog is not None:
        drive.watchdog.stop()
    if drive.safety_process is not None:
        drive.safety_process.stop()
    for e in drive.entries:
        if not e.actuator:
            continue
        attach = getattr(e.part, "attach", None)
        if callable(attach):
            attach(None)


def _last_event(guard: SafetyProcess, i: int) -> Callable[[], tuple[float, float]]:
    return lambda: guard.last_event(i)


def _run_end_latency(record: Recorder, origins: dict[str, float], e: Entry) -> Callable[[float], None] | None:
    """For an actuator that writes inside its ``run()``: ``latency(t_end)`` records the end of its run minus the
    origin of its first input (its command). ``None`` for an actuator without inputs (nothing to measure)."""
    k = next((i for i in e.inputs if i is not None), None)
    if k is None:
        return None
    oget = origins.get

    def latency(t_end: float) -> None:
        o = oget(k)
        if o is not None:
            record(t_end, o)

    return latency
