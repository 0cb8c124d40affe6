"""Pipelined parts: beside the ticks, started by the tick or by a new frame, with true data ages."""

import asyncio
import threading

import pytest

from asyncdonkey import PartError, PartSpecError, Vehicle, get_clock
from asyncdonkey.latest import Latest

RATE = 20

#: the cameras here are stand-ins that write frame *numbers* to ``cam/image_array`` (what is measured is when each
#: frame is seen, not its pixels), which that channel's contract (a uint8 image) rightly refuses in checked mode
pytestmark = pytest.mark.asyncdonkey_checked(False)


class TickCamera:
    """A camera read in the tick: its frame is sensed when the tick reads it."""

    def __init__(self) -> None:
        self.n = 0

    def run(self):
        self.n += 1
        return self.n


class PushCamera:
    """A camera that captures on its own schedule (offset from the ticks) and pushes each frame."""

    def __init__(self, hz: float, offset: float) -> None:
        self.hz = hz
        self.offset = offset
        self.frames: Latest[int] = Latest()
        self.n = 0

    async def update(self):
        clock = get_clock()
        t0 = clock.now() + self.offset
        k = 0
        while True:
            await clock.sleep_until(t0 + k / self.hz)
            self.n += 1
            self.frames.publish(self.n, clock.now())
            k += 1

    def run(self):
        s = self.frames.sample
        return None if s is None else s.value

    def output_origin(self):
        s = self.frames.sample
        return None if s is None else s.timestamp

    def subscribe(self, callback):
        return self.frames.subscribe(callback)


class SlowPilot:
    """Inference that costs ``seconds`` of (virtual) time; records which frame each result came from."""

    def __init__(self, seconds: float, die_after: int | None = None) -> None:
        self.seconds = seconds
        self.die_after = die_after
        self.frames_seen: list[int] = []

    async def run(self, frame):
        await asyncio.sleep(self.seconds)
        self.frames_seen.append(frame)
        if self.die_after is not None and len(self.frames_seen) > self.die_after:
            raise RuntimeError("inference failed")
        return 0.0 + 0.0, 0.5 + 0.0


class Actuator:
    """Records (time, throttle, age of its sensing) whenever it runs."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float]] = []

    def run(self, throttle, age):
        self.rows.append((get_clock().now(), throttle, age))

    def safe_state_sync(self):
        pass


def _car(pilot, *, camera=None, pipelined=True, trigger=None, react=False, on_error="stop"):
    v = Vehicle()
    cam = camera or TickCamera()
    v.add(cam, outputs=["cam/image_array"])
    v.add(
        pilot,
        inputs=["cam/image_array"],
        outputs=["pilot/angle", "pilot/throttle"],
        pipelined=pipelined,
        trigger=trigger,
        on_error=on_error,
    )
    act = Actuator()
    v.add(act, inputs=["pilot/throttle", "pilot/throttle@age"], react=react, name="throttle")
    return v, act


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_an_80ms_pilot_in_order_slows_the_loop_to_12_5_hz():
    v, _ = _car(SlowPilot(0.08), pipelined=False)
    report = await v.run(RATE, 50)
    assert report.achieved_hz == pytest.approx(12.5)
    assert report.overruns == 50


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_pipelined_the_loop_keeps_20_hz_and_the_pilot_runs_at_its_own_rate():
    pilot = SlowPilot(0.08)
    v, act = _car(pilot)
    report = await v.run(RATE, 100)
    assert report.achieved_hz == pytest.approx(20.0)
    assert report.overruns == 0
    p = report.pipelined["SlowPilot"]
    # a tick's start request while it computes is served as soon as it is free: back to back, 80 ms each
    assert p["rate_hz"] == pytest.approx(1 / 0.08)
    assert p["runs"] == 62
    # every command is as old as its frame: read when the pilot became free, 80 ms of inference, then
    # re-read by the ticks until the next result
    ages = [age for _t, thr, age in act.rows if thr is not None]
    assert min(ages) >= 0.08 - 1e-9 and max(ages) <= 0.08 + 0.05 + 0.08 + 1e-9
    assert "pipelined SlowPilot" in v.format_report(report)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_pipelined_sync_part_computes_off_the_loop_thread():
    seen = []

    class SyncPilot:
        def run(self, frame):
            seen.append(threading.current_thread() is threading.main_thread())
            return frame * 2

    v = Vehicle()
    v.add(TickCamera(), outputs=["cam"])
    v.add(SyncPilot(), inputs=["cam"], outputs=["out"], pipelined=True)
    await v.run(RATE, 5)
    assert seen and not any(seen)
    assert v.mem["out"] % 2 == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_dead_pipelined_pilot_ages_into_the_failsafe():
    pilot = SlowPilot(0.04, die_after=5)
    v, act = _car(pilot, on_error="continue")
    report = await v.run(RATE, 40)
    assert report.part_errors == {"SlowPilot": pilot.frames_seen.__len__() - 5}
    ages = [age for _t, _thr, age in act.rows]
    assert ages[-1] > 1.0  # the last good command ages without bound: the failsafe sees it


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_pipelined_failure_with_on_error_stop_stops_the_car():
    v, _ = _car(SlowPilot(0.01, die_after=2))
    with pytest.raises(PartError, match=r"part 'SlowPilot' failed in its background task: RuntimeError"):
        await v.run(RATE, 100)
    assert v.last_report.loops < 10


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_frame_started_and_reacting_cuts_the_latency_to_the_inference():
    cam = PushCamera(hz=20, offset=0.013)  # frames 13 ms after each tick: a tick-started pilot sees them late
    pilot = SlowPilot(0.03)
    v, act = _car(pilot, camera=cam, trigger="cam/image_array", react=True)
    report = await v.run(RATE, 60)
    p = report.pipelined["SlowPilot"]
    assert p["rate_hz"] == pytest.approx(20.0)  # one run per frame
    assert p["superseded"] == 0
    reacted = [(t, age) for t, thr, age in act.rows if thr is not None and age < 0.031]
    assert reacted and all(age == pytest.approx(0.03) for _t, age in reacted)  # capture → output: inference only
    # the frames the pilot saw are consecutive: every frame, none skipped
    assert pilot.frames_seen == list(range(pilot.frames_seen[0], pilot.frames_seen[0] + len(pilot.frames_seen)))


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_pilot_slower_than_the_camera_skips_to_the_newest_frame():
    cam = PushCamera(hz=50, offset=0.001)
    pilot = SlowPilot(0.08)
    v, _ = _car(pilot, camera=cam, trigger="cam/image_array")
    report = await v.run(RATE, 40)
    p = report.pipelined["SlowPilot"]
    assert p["superseded"] > 0
    gaps = {b - a for a, b in zip(pilot.frames_seen, pilot.frames_seen[1:], strict=False)}
    # 80 ms of inference at 50 fps: 4 frame periods. It takes the newest frame when it becomes free (the
    # frame due at exactly +80 ms arrives just after it), never a backlog of old ones
    assert gaps <= {3, 4}


def test_pipelined_options_are_checked_at_add():
    v = Vehicle()
    with pytest.raises(PartSpecError, match="trigger 'x' must be one of the part's inputs"):
        v.add(SlowPilot(0.1), inputs=["cam"], outputs=["a", "b"], pipelined=True, trigger="x")
    with pytest.raises(PartSpecError, match="add it with pipelined=True"):
        v.add(SlowPilot(0.1), inputs=["cam"], outputs=["a", "b"], trigger="cam")
    with pytest.raises(PartSpecError, match="react=True is for parts downstream"):
        v.add(SlowPilot(0.1), inputs=["cam"], outputs=["a", "b"], pipelined=True, react=True)
    with pytest.raises(PartSpecError, match="pipelined must be True or False"):
        v.add(SlowPilot(0.1), inputs=["cam"], pipelined="yes")


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_react_parts_run_when_a_push_source_publishes_not_at_the_next_tick():
    cam = PushCamera(hz=20, offset=0.013)  # captures 13 ms after each tick

    class Sender:
        """A react part fed by the camera (a publisher sending frames off the car, say)."""

        def __init__(self):
            self.rows = []

        def run(self, frame, age):
            self.rows.append((get_clock().now(), frame, age))

    sender = Sender()
    v = Vehicle()
    v.add(cam, outputs=["cam/image_array"])
    v.add(sender, inputs=["cam/image_array", "cam/image_array@age"], react=True)
    await v.run(RATE, 20)
    pushed = [(t, f, age) for t, f, age in sender.rows if age == 0.0]
    # every frame reached it the moment it was captured (13 ms after a tick), besides the tick's own run
    assert len(pushed) >= 18
    assert all(round((t - 0.013) * RATE, 6) % 1 == 0 for t, _f, _a in pushed)
