"""A pilot server's figures count what they say: frames, batches, model calls, and the time of each.

Three batches of 3, 2 and 1 frames are 6 frames in 3 batches whatever the model; a model whose batch is fixed
at 1 makes 6 model calls of them, one with a dynamic batch 3. The batching runs on the virtual clock with the
real ONNX pilot (its work runs in the loop's worker thread and costs no virtual time); a model call's time is
read from a timer the test steps, so the times are exact too.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.clock import get_clock
from asyncdonkey.parts.zenoh.batch_infer import BatchPilot, dynamic_batch_onnx
from asyncdonkey.parts.zenoh.batcher import BatchLoop, FrameBatcher
from asyncdonkey.parts.zenoh.server_figures import ServerFigures

MODELS = Path(__file__).resolve().parents[2] / "examples" / "models"
FRAME = np.zeros((120, 160, 3), np.uint8)


@pytest.fixture(scope="module")
def batchable(tmp_path_factory) -> Path:
    return dynamic_batch_onnx(MODELS / "sim_pilot.onnx", tmp_path_factory.mktemp("model") / "sim_pilot_batch.onnx")


@pytest.fixture(scope="module")
def batchable_models(batchable) -> tuple[BatchPilot, BatchPilot]:
    """The shipped pilot (batch fixed at 1) and its batchable copy, loaded once for every example."""
    return BatchPilot(MODELS / "sim_pilot.onnx"), BatchPilot(batchable)


def _ms_timer(step_s: float = 0.001) -> Callable[[], float]:
    """A timer that moves ``step_s`` at each reading: every model call (two readings) takes exactly that."""
    ticks = itertools.count()
    return lambda: next(ticks) * step_s


class Answers:
    """The loop's answer callback: how many commands each car got."""

    def __init__(self) -> None:
        self.cars: dict[str, int] = {}

    def __call__(self, frame: Any, command: tuple[float, float], now: float) -> None:
        self.cars[frame.car] = self.cars.get(frame.car, 0) + 1


def _counters(loop: BatchLoop, answers: Answers) -> dict[str, dict[str, int]]:
    """The per-car counters as the pilot server gives them: the batcher's, plus the commands sent."""
    out = loop.batcher.counters()
    for car, row in out.items():
        row["answered"] = answers.cars.get(car, 0)
    return out


async def _three_batches(infer: Any) -> tuple[BatchLoop, Answers]:
    """Batches of 3, 2 and 1 frames (cars a, b, c within one window; then a, b; then a), each window 5 ms and
    each batch well after the last."""
    answers = Answers()
    loop = BatchLoop(FrameBatcher(window_s=0.005, max_age_s=0.25), infer, answers)
    serving = asyncio.ensure_future(loop.serve())
    clock = get_clock()
    for cars in (["a", "b", "c"], ["a", "b"], ["a"]):
        for car in cars:
            loop.offer(car, FRAME, clock.now())
            await clock.sleep(0.001)
        await clock.sleep(0.05)
    loop.stop()
    await serving
    loop.close()
    return loop, answers


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.parametrize("dynamic", [False, True], ids=["fixed-batch-1", "dynamic-batch"])
async def test_six_frames_in_three_batches_are_six_model_calls_at_batch_1_and_three_when_batchable(dynamic, batchable):
    model = BatchPilot(batchable if dynamic else MODELS / "sim_pilot.onnx", timer=_ms_timer())
    assert model.batched is dynamic
    loop, answers = await _three_batches(model.infer)
    assert list(loop.batch_sizes) == [3, 2, 1] and loop.batches == 3 and loop.frames == 6
    calls = 3 if dynamic else 6
    assert model.calls == calls and model.frames == 6 and list(model.call_s) == pytest.approx([0.001] * calls)
    figures = ServerFigures.of(loop, model, _counters(loop, answers))
    assert (figures.frames_received, figures.frames_inferred, figures.frames_answered) == (6, 6, 6)
    assert figures.batches == 3 and figures.frames_per_batch == 2.0
    assert figures.model_calls == calls and figures.frames_per_call == 6 / calls
    assert figures.call_ms == (pytest.approx(1.0), pytest.approx(1.0))
    line = figures.line()
    assert line.startswith("frames 6 received, 6 inferred, 6 answered (0 late), 0 too old, 0 replaced | ")
    assert "| 3 batches, 2.00 frames per batch, per batch p50 " in line
    assert f"| {calls} model calls, {6 / calls:.2f} frames per call, per call p50 1.00 ms p99 1.00 ms |" in line
    assert line.endswith("answered/received per car: a 3/3; b 2/2; c 1/1")


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_model_that_does_not_count_its_calls_leaves_them_unknown_and_batches_are_timed():
    """A plain coroutine model of 2 ms a frame: the batch times are its, on the virtual clock; its calls are
    not guessed from the batches."""

    async def infer(frames):
        await asyncio.sleep(0.002 * len(frames))
        return [(0.0, 0.3)] * len(frames)

    loop, answers = await _three_batches(infer)
    assert [round(t, 9) for t in loop.batch_s] == [0.006, 0.004, 0.002]
    figures = ServerFigures.of(loop, infer, _counters(loop, answers))
    assert figures.model_calls is None and figures.call_ms is None and figures.frames_per_call is None
    assert figures.batch_ms is not None and figures.batch_ms[0] == pytest.approx(4.0)
    line = figures.line()
    assert "| 3 batches, 2.00 frames per batch, per batch p50 4.00 ms p99 5.96 ms |" in line
    assert "| model calls not counted by this model |" in line


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_frames_without_a_command_and_failed_batches_are_counted_apart():
    """A model that gives no command for car b (as for a NaN) and fails on its third batch: inferred counts the
    frames the model answered for, answered the commands sent, failed the batch it raised on."""
    calls = 0

    async def infer(frames):
        nonlocal calls
        calls += 1
        if calls == 3:
            raise RuntimeError("the runtime failed")
        return [None if k == 1 else (0.0, 0.3) for k in range(len(frames))]

    loop, answers = await _three_batches(infer)
    figures = ServerFigures.of(loop, infer, _counters(loop, answers))
    assert (figures.frames_received, figures.frames_inferred, figures.frames_answered) == (6, 5, 3)
    assert figures.batches == 2 and figures.failed_batches == 1
    assert "frames 6 received, 5 inferred, 3 answered (0 late)" in figures.line()
    assert "| 2 batches (1 failed), 2.50 frames per batch," in figures.line()


def test_late_and_too_old_are_shown_per_car_and_in_total():
    cars = {
        "car1": {"frames": 10, "replaced": 1, "too_old": 2, "batched": 7, "answered": 7, "late": 3},
        "car2": {"frames": 5, "replaced": 0, "too_old": 0, "batched": 5, "answered": 5, "late": 0},
    }
    loop = BatchLoop(FrameBatcher(window_s=0.005, max_age_s=0.25), lambda frames: [], lambda *a: None)
    loop.batches, loop.frames = 6, 12
    figures = ServerFigures.of(loop, None, cars, withheld=2)
    line = figures.line()
    assert line.startswith("frames 15 received, 12 inferred, 12 answered (3 late), 2 too old, 1 replaced, 2 withheld")
    assert line.endswith("answered/received per car: car1 7/10 late 3 too_old 2; car2 5/5")


@settings(max_examples=25)
@given(sizes=st.lists(st.integers(1, 6), min_size=1, max_size=5), max_batch=st.integers(1, 4))
def test_a_models_calls_are_one_per_frame_at_batch_1_and_one_per_max_batch_chunk_when_batchable(
    batchable_models, sizes, max_batch
):
    """Whatever the batches and ``max_batch``: a model of batch 1 makes one call per frame; a batchable one
    makes ``ceil(size / max_batch)`` calls per batch; both count every frame once and time every call."""
    for model in batchable_models:
        model.max_batch = max_batch
        calls0, frames0, timed0 = model.calls, model.frames, len(model.call_s)
        for n in sizes:
            assert len(model.infer([FRAME] * n)) == n
        expected = sum(sizes) if not model.batched else sum(-(-n // max_batch) for n in sizes)
        assert model.calls - calls0 == expected and model.frames - frames0 == sum(sizes)
        assert len(model.call_s) - timed0 == expected


def test_a_warm_up_call_is_not_a_model_call_of_the_cars(batchable_models):
    """A server of a pair calls its model once on a blank frame before it answers (the runtime's first call is
    slow): that call runs the model but is not counted as one of the cars' calls, frames or call times."""
    pilot = BatchPilot(MODELS / "sim_pilot.onnx")
    pilot.warm_up()
    assert (pilot.calls, pilot.frames, len(pilot.call_s)) == (0, 0, 0)
    figures = ServerFigures.of(BatchLoop(FrameBatcher(0.005, 0.25, 8), pilot.infer, Answers()), pilot, {})
    assert figures.model_calls == 0 and figures.call_ms is None
    # the cars' calls count from the first as before, with the same commands as a pilot that never warmed up
    assert pilot.infer([FRAME]) == batchable_models[0].infer([FRAME])
    assert (pilot.calls, pilot.frames, len(pilot.call_s)) == (1, 1, 1)
