"""A pilot server too slow for its cars, and frames too old when they reach it: each car's own failsafe decides.

On 127.0.0.1, in one process: the pilot server with the shipped ONNX pilot (batch fixed at 1: one model call per
frame), and a car as ``examples/car.py --pilot remote`` is one: its camera's frames out, the one-sample command
in, and its real :class:`~asyncdonkey.parts.failsafe.StaleCommandStop` (250 ms, the server's ``max_age_s``)
writing the throttle the car would drive.

* **The server slowed past the window** (each model call 400 ms): the batcher takes each car's *newest* frame,
  so the frames it takes are fresh and are inferred, but every command leaves the server already older than the
  window. The figures count them as answered ``late``; the car's failsafe holds its throttle at 0.0 however
  many such commands come, and the car drives again when the server is fast again.
* **Frames too old when they reach the server** (the car's camera stalls: its last frame is sent again each
  tick with its capture time, as ``PiCamera`` does): once older than the window they are counted ``too_old``
  and not inferred (the model's call count stops), no command comes, and the car's failsafe stops it.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.clock import get_clock
from asyncdonkey.parts.failsafe import StaleCommandStop
from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohLink, ZenohPublisher, ZenohSubscriber
from asyncdonkey.parts.zenoh.batch_infer import BatchPilot

from ..waiting import await_until
from .fleet_car import ThrottleLog, record_sim_frames
from .zenoh_loopback import connector, free_port, listener

MODELS = Path(__file__).resolve().parents[2] / "examples" / "models"
FAILSAFE_S = 0.25
SLOW_S = 0.4  # a model call past the window
CMD = ["pilot/angle", "pilot/throttle"]
#: a late tick on a loaded 2-core machine
SLACK_S = 0.5


class SlowedPilot(BatchPilot):
    """The shipped pilot; while :attr:`slow_s` is set, each model call also takes that long (an overloaded
    server), which its call count and call times see as they would a slow model."""

    slow_s = 0.0

    def _run(self, images: Any) -> list[np.ndarray]:
        if self.slow_s:
            time.sleep(self.slow_s)
        return super()._run(images)


class Camera:
    """Recorded frames, one per tick, each dated by its capture. :meth:`stall` freezes it: the last frame again
    each tick with its capture time as origin, so the frame the car sends ages (as ``PiCamera``'s does)."""

    def __init__(self, frames: np.ndarray) -> None:
        self.frames = frames
        self.k = 0
        self.stalled = False
        self.captured: float | None = None
        self.frame = frames[0]

    def run(self) -> np.ndarray:
        if not self.stalled:
            self.k += 1
            self.frame = self.frames[self.k % len(self.frames)].copy()
            self.captured = get_clock().now()
        return self.frame

    def output_origin(self) -> float | None:
        return self.captured

    def stall(self) -> None:
        self.stalled = True


class Car:
    """One car on the server: camera → ZenohPublisher; command ZenohSubscriber → StaleCommandStop → throttle."""

    def __init__(self, link: ZenohLink, frames: np.ndarray) -> None:
        self.vehicle = v = Vehicle()
        self.camera = Camera(frames)
        v.add(self.camera, outputs=["cam/image_array"])
        out = ZenohPublisher(link, ["cam/image_array"])
        v.add(out, inputs=out.inputs)
        self.commands = ZenohSubscriber(link, CMD, group=PILOT_COMMAND)
        v.add(self.commands, outputs=CMD)
        self.failsafe = StaleCommandStop(FAILSAFE_S)
        v.add(self.failsafe, inputs=["pilot/throttle", "pilot/throttle@age"], outputs=["car/throttle"])
        self.log = ThrottleLog()
        v.add(self.log, inputs=["car/throttle"])

    def throttles(self, t0: float, t1: float = float("inf")) -> list[tuple[float, Any]]:
        """The throttle's changes between ``t0`` and ``t1`` (monotonic), as (seconds after ``t0``, value)."""
        return [(t - t0, v) for t, v in self.log.changes if t0 <= t < t1]

    def moving(self) -> bool:
        return isinstance(self.log.last, float) and self.log.last > 0


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> np.ndarray:
    return record_sim_frames(str(tmp_path_factory.mktemp("frames") / "frames.npy"), count=12)


class Fleet:
    """The server and one car, started and stopped around a test."""

    def __init__(self, frames: np.ndarray) -> None:
        from asyncdonkey.parts.zenoh import PilotServer

        port = free_port()
        self.model = SlowedPilot(MODELS / "sim_pilot.onnx")
        self.server = PilotServer(self.model, ["car1"], config=listener(port), max_age_s=FAILSAFE_S)
        self.link = ZenohLink("cars/car1", connector(port))
        self.car = Car(self.link, frames)

    async def __aenter__(self) -> Fleet:
        self.serving = asyncio.ensure_future(self.server.serve())
        self.drive = asyncio.ensure_future(self.car.vehicle.run(rate_hz=20, duration=30))
        await await_until(lambda: self.car.commands.received >= 10 and self.car.moving(), timeout=15,
                          what=lambda: f"the car driving on the server: {self.server.figures().line()}")  # fmt: skip
        return self

    async def __aexit__(self, *exc: Any) -> None:
        self.car.vehicle.stop()
        await asyncio.wait_for(self.drive, 10)
        self.server.stop()
        await asyncio.wait_for(self.serving, 10)
        self.server.close()
        self.link.close()


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_server_slower_than_the_window_answers_late_and_the_cars_failsafe_holds_it_stopped(frames):
    from asyncdonkey.commands.zenoh import _stats_line

    async with Fleet(frames) as fleet:
        car, model = fleet.car, fleet.model
        before = fleet.server.counters()["car1"]
        t_slow = time.monotonic()
        model.slow_s = SLOW_S
        await asyncio.sleep(2.0)
        during = fleet.server.counters()["car1"]
        line = _stats_line(fleet.server)
        t_fast = time.monotonic()
        model.slow_s = 0.0
        await await_until(car.moving, timeout=5, what="the car driving again once the server is fast")
    slowed = car.throttles(t_slow, t_fast)
    # the last fresh command ages past the window 250 ms after the slowdown; the next tick holds 0.0
    first_zero = next((t for t, v in slowed if v == 0.0), None)
    assert first_zero is not None and first_zero < FAILSAFE_S + 0.05 + SLACK_S, slowed
    # and no command of the slowed server moves the car again: each left it already older than the window
    assert all(v == 0.0 for t, v in slowed if t >= first_zero), slowed
    answered = during["answered"] - before["answered"]
    late = during["late"] - before["late"]
    assert answered >= 2 and late >= answered - 1, (before, during)  # all late but the call already under way
    # the frames taken were the car's newest, fresh when taken: inferred (one model call each), not too old
    assert model.calls == fleet.server.loop.frames == model.frames
    assert f"late {during['late']}" in line and "1.00 frames per call" in line, line
    figures = fleet.server.figures()
    assert figures.call_ms is not None and figures.call_ms[1] >= SLOW_S * 1e3 * 0.9, figures


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_frames_too_old_when_they_reach_the_server_are_counted_not_inferred_and_the_car_stops(frames):
    async with Fleet(frames) as fleet:
        car, model = fleet.car, fleet.model
        t_stall = time.monotonic()
        car.camera.stall()
        await asyncio.sleep(0.8)
        calls_then, too_old_then = model.calls, fleet.server.counters()["car1"]["too_old"]
        await asyncio.sleep(1.0)
        counters = fleet.server.counters()["car1"]
        stats = fleet.server.figures()
    # the frame the car sends is older than the window from 250 ms after the stall: from then on not inferred
    assert model.calls == calls_then, "a frame older than the window was inferred"
    assert counters["too_old"] - too_old_then >= 10, counters  # 20 frames a second, counted
    assert stats.frames_too_old == counters["too_old"] and stats.model_calls == stats.frames_inferred
    assert f"car1 {counters['answered']}/{counters['frames']} too_old {counters['too_old']}" in stats.line()
    # no command for it, so the car's own failsafe stopped it and holds it
    after = car.throttles(t_stall)
    first_zero = next((t for t, v in after if v == 0.0), None)
    assert first_zero is not None and first_zero < FAILSAFE_S + 0.05 + SLACK_S, after
    assert after[-1][1] == 0.0 and car.failsafe.active, after
