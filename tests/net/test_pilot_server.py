"""A fleet on one pilot server.

The batching rules on the virtual clock, without Zenoh (window, fairness, too old, order, a slow model); the
batched model against the pilot part's own answers (ONNX with a dynamic batch, ONNX fixed at 1, TFLite resized,
``--gpu`` on a machine without CUDA); then the fleet as processes on loopback with the configs of
``zenoh-pair --fleet``: four cars and a flooding one drive on the server, a car of another CA gets nothing, and
killing the server stops every car by its own stale-command stop.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
import types
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey.clock import get_clock
from asyncdonkey.parts.zenoh.batch_infer import BatchPilot, dynamic_batch_onnx
from asyncdonkey.parts.zenoh.batcher import BatchLoop, Frame, FrameBatcher

from ..waiting import wait_until
from .fleet_car import SCRIPT, FleetProcess, record_sim_frames

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "examples" / "models"
FAILSAFE_S = 0.25


# -- the rules, on the virtual clock ---------------------------------------------------------------------------
class Model:
    """An async model that costs ``cost_s`` of (virtual) time per call and answers each frame with its number."""

    def __init__(self, cost_s: float = 0.002) -> None:
        self.cost_s = cost_s
        self.batches: list[tuple[float, list[str]]] = []

    async def infer(self, images):
        self.batches.append((get_clock().now(), [img for img in images]))
        await asyncio.sleep(self.cost_s)
        return [(0.0, 0.5) for _ in images]


def _loop(window_s: float = 0.005, max_age_s: float = 0.25, cost_s: float = 0.002, max_batch=None):
    model = Model(cost_s)
    answers: list[tuple[float, str, float]] = []
    loop = BatchLoop(
        FrameBatcher(window_s=window_s, max_age_s=max_age_s, max_batch=max_batch),
        model.infer,
        lambda frame, command, now: answers.append((now, frame.image, frame.origin)),
    )
    return loop, model, answers


async def _at(t: float, fn, *args) -> None:
    clock = get_clock()
    await clock.sleep_until(t)
    fn(*args)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_frames_within_the_window_share_one_call_in_arrival_order():
    loop, model, answers = _loop(window_s=0.005, cost_s=0.002)
    server = asyncio.ensure_future(loop.serve())
    t0 = get_clock().now()
    # three cars within 4 ms; a fourth frame after the window closed
    await asyncio.gather(
        _at(t0 + 0.001, loop.offer, "b", "b1", t0),
        _at(t0 + 0.003, loop.offer, "a", "a1", t0 + 0.002),
        _at(t0 + 0.004, loop.offer, "c", "c1", t0 + 0.003),
        _at(t0 + 0.0065, loop.offer, "a", "a2", t0 + 0.006),
    )
    await get_clock().sleep(0.05)
    loop.stop()
    await server
    (t1, first), (t2, second) = model.batches
    assert first == ["b1", "a1", "c1"]  # one call, arrival order
    assert t1 == pytest.approx(t0 + 0.006)  # the window opened by the first frame (1 ms) closed 5 ms later
    assert second == ["a2"]
    assert t2 == pytest.approx(t0 + 0.0115)  # its own window: opened at 6.5 ms
    # each answer carries its own frame's origin, sent when its call returned
    assert answers[:3] == [(t0 + 0.008, "b1", t0), (t0 + 0.008, "a1", t0 + 0.002), (t0 + 0.008, "c1", t0 + 0.003)]
    assert loop.batches == 2 and loop.frames == 4 and list(loop.batch_sizes) == [3, 1]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_flooding_car_gets_one_slot_per_batch_and_the_others_lose_nothing():
    loop, model, answers = _loop(window_s=0.005, cost_s=0.010)
    server = asyncio.ensure_future(loop.serve())
    clock = get_clock()
    t0 = clock.now()
    sent = {"car1": 0, "car2": 0}

    async def car(name: str, period: float, offset: float) -> None:
        k = 0
        while True:
            await clock.sleep_until(t0 + offset + k * period)
            t = clock.now()
            if t > t0 + 1.0:
                return
            loop.offer(name, f"{name}#{k}", t)
            if name in sent:
                sent[name] += 1
            k += 1

    # a flooder at 1 kHz beside two cars at 20 Hz, a model call of 10 ms
    await asyncio.gather(car("flood", 0.001, 0.0), car("car1", 0.05, 0.0102), car("car2", 0.05, 0.0371))
    await clock.sleep(0.1)
    loop.stop()
    await server
    for _, frames in model.batches:
        cars = [f.split("#")[0] for f in frames]
        assert len(cars) == len(set(cars))  # never two frames of one car in a call
    for name in ("car1", "car2"):
        answered = [img for _, img, _ in answers if img.startswith(name)]
        assert len(answered) == sent[name] == 20  # every frame of the 20 Hz cars answered
    counters = loop.batcher.counters()
    assert counters["flood"]["replaced"] > 800 and counters["car1"]["replaced"] == 0
    # no frame of a 20 Hz car waited more than one window plus one model call plus the call before it
    for _, img, origin in answers:
        if not img.startswith("flood"):
            now = next(t for t, i, _ in answers if i == img)
            assert now - origin <= 0.005 + 0.010 + 0.010 + 1e-9


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_frames_older_than_the_failsafe_window_are_not_inferred():
    loop, model, answers = _loop(window_s=0.005, max_age_s=0.25, cost_s=0.2)  # a model call of 200 ms
    server = asyncio.ensure_future(loop.serve())
    clock = get_clock()
    t0 = clock.now()
    loop.offer("car1", "fresh", t0)
    await clock.sleep(0.01)  # its call runs from 5 ms to 205 ms; meanwhile, at 10 ms:
    loop.offer("car2", "waits", t0 + 0.01)  # 195 ms old when its batch is taken at 205 ms: inferred
    loop.offer("car3", "old", t0 - 0.1)  # 305 ms old by then
    loop.offer("car4", "aged-waiting", t0 - 0.05)  # 60 ms old on arrival, 255 ms when its turn comes
    await clock.sleep(0.6)
    loop.stop()
    await server
    assert [frames for _, frames in model.batches] == [["fresh"], ["waits"]]
    counters = loop.batcher.counters()
    assert counters["car3"]["too_old"] == 1 and counters["car4"]["too_old"] == 1
    assert counters["car2"] == {"frames": 1, "replaced": 0, "too_old": 0, "batched": 1}
    assert [img for _, img, _ in answers] == ["fresh", "waits"]


def test_max_batch_serves_the_earliest_arrivals_first_and_the_rest_next():
    b = FrameBatcher(window_s=0.005, max_age_s=0.25, max_batch=2)
    for k, car in enumerate(["c", "a", "b"]):
        b.offer(Frame(car, car, origin=0.0, arrival=k * 0.001))
    assert b.due() == pytest.approx(0.005)
    assert [f.car for f in b.take(0.005)] == ["c", "a"]
    assert b.due() == pytest.approx(0.007)  # already closed: b is next, at once
    b.offer(Frame("c", "c2", origin=0.006, arrival=0.006))
    assert [f.car for f in b.take(0.0071)] == ["b", "c"]  # b arrived first
    assert b.due() is None and b.take(1.0) == []


def test_batcher_settings_are_checked():
    with pytest.raises(ValueError, match="window_s"):
        FrameBatcher(window_s=-1, max_age_s=0.25)
    with pytest.raises(ValueError, match="max_age_s"):
        FrameBatcher(window_s=0.005, max_age_s=0)
    with pytest.raises(ValueError, match="max_batch"):
        FrameBatcher(window_s=0.005, max_age_s=0.25, max_batch=0)


# -- the batched model ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> tuple[Path, np.ndarray]:
    path = tmp_path_factory.mktemp("frames") / "frames.npy"
    return path, record_sim_frames(str(path), count=12)


@pytest.fixture(scope="module")
def batchable(tmp_path_factory) -> Path:
    return dynamic_batch_onnx(MODELS / "sim_pilot.onnx", tmp_path_factory.mktemp("model") / "sim_pilot_batch.onnx")


def _flat(commands) -> list[float]:
    return [x for command in commands for x in command]


def test_one_call_answers_each_frame_as_the_pilot_part_does(frames, batchable, caplog):
    _, images = frames
    images = list(images[:5])
    with caplog.at_level(logging.WARNING):
        fixed = BatchPilot(MODELS / "sim_pilot.onnx")
    assert not fixed.batched and caplog.text.count("fixed batch of 1") == 1  # said once, at load
    alone = [fixed.pilot.predict(img) for img in images]
    assert (
        _flat(fixed.infer(images)) == pytest.approx(_flat(alone), abs=1e-6) and fixed.calls == 5
    )  # one call per frame
    batched = BatchPilot(batchable)
    assert batched.batched
    assert _flat(batched.infer(images)) == pytest.approx(_flat(alone), abs=1e-5) and batched.calls == 1
    assert all(0 < t < 1 for _, t in alone)  # a real pilot's throttle on real frames, not a saturated one
    lite = BatchPilot(MODELS / "sim_pilot.tflite")
    assert lite.batched  # dynamic batch (-1) in its signature: resized to the batch
    assert _flat(lite.infer(images)) == pytest.approx(_flat([lite.pilot.predict(i) for i in images]), abs=1e-5)
    assert _flat(lite.infer(images[:2])) == pytest.approx(_flat([lite.pilot.predict(i) for i in images[:2]]), abs=1e-5)
    assert lite.calls == 2
    with pytest.raises(ValueError, match=r"a frame is \(10, 10, 3\) uint8"):
        batched.infer([np.zeros((10, 10, 3), np.uint8)])


def test_gpu_on_a_machine_without_cuda_warns_and_runs_on_the_cpu(batchable, caplog):
    import onnxruntime as ort

    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this machine has CUDA: the fallback is not reachable here")
    with caplog.at_level(logging.WARNING):
        model = BatchPilot(batchable, gpu=True)
    assert model.provider == "CPUExecutionProvider"
    assert "--gpu asked, but this onnxruntime has no CUDA provider" in caplog.text and "onnxruntime-gpu" in caplog.text
    assert len(model.infer([np.zeros((120, 160, 3), np.uint8)] * 3)) == 3


# -- the fleet, as processes on loopback -----------------------------------------------------------------------
@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.subprocess
def test_a_fleet_drives_on_one_server_and_stops_when_it_dies(tmp_path, frames, batchable):
    from asyncdonkey.parts.zenoh.pairing import make_fleet

    from .zenoh_loopback import free_port

    port = free_port()
    cars = ["car1", "car2", "car3", "car4"]
    fleet = make_fleet(
        tmp_path / "fleet", cars=[*cars, "flood"], server="pilot", server_hosts=["127.0.0.1"], port=port,
        listen_host="127.0.0.1",
    )  # fmt: skip
    # a car paired with another server (its own CA): pointed at this server's port, named as one it serves
    other = make_fleet(
        tmp_path / "other", cars=["car9"], server="pilot", server_hosts=["127.0.0.1"], port=port,
        listen_host="127.0.0.1",
    )  # fmt: skip
    frames_path = str(frames[0])
    car_script = str(SCRIPT)
    server = FleetProcess([
        "-m", "asyncdonkey.commands", "pilot-server", str(batchable), "--cars", *cars, "flood", "car9",
        "--config", str(fleet.server_config), "--stats-every", "0",
    ], cwd=ROOT)  # fmt: skip
    fleet_cfg = str(tmp_path / "fleet" / "{car}" / "car.json5")
    procs = [
        FleetProcess([car_script, "--frames", frames_path, "--car", car, "--config", fleet_cfg], cwd=ROOT)
        for car in cars
    ]
    flood = FleetProcess(
        [car_script, "--frames", frames_path, "--car", "flood", "--config", fleet_cfg, "--hz", "200"], cwd=ROOT
    )
    foreign = FleetProcess(
        [car_script, "--frames", frames_path, "--car", "car9", "--config", str(other.car_configs["car9"])], cwd=ROOT
    )
    everyone = [*procs, flood, foreign]
    try:
        driving = lambda: all(p.of("driving") for p in [*procs, flood])  # noqa: E731
        wait_until(
            driving,
            45,
            lambda: "every car to drive: " + "".join(p.lines[-1] if p.lines else "" for p in everyone),
            0.05,
        )
        t_all = max(p.of("driving")[0]["t"] for p in [*procs, flood])
        time.sleep(3.0)  # all five drive on the server, the flooder at 200 frames/s
        t_kill = time.monotonic()
        server.p.send_signal(signal.SIGKILL)
        server.stop()
        time.sleep(1.0)
    finally:
        for p in everyone:
            p.stop()
        server.stop()
    reports = {r["car"]: r for p in everyone for r in p.of("report")}
    assert set(reports) == {*cars, "flood", "car9"}, [p.lines[-3:] for p in everyone]
    for car in [*cars, "flood"]:
        r = reports[car]
        # commands arrived, each with its own frame's origin: the latency the car measures is frame to command,
        # a few ms here (it would be the command's own send age, ~0, if the origin were not carried back)
        steady = [t for t in r["arrivals"] if t_all + 0.5 < t < t_kill]
        lat = r["latency_ms"]
        assert lat and min(lat) > 0 and float(np.median(lat)) < FAILSAFE_S * 1e3, (car, lat[:20])
        # the loopback trip alone is 0.1-0.5 ms; a frame's trip adds the way out, the window and the model
        assert float(np.median(lat)) > 1.0, (car, lat[:20])
        # every car is answered at (about) its rate: one 20 Hz car is not starved by the flooder
        if car != "flood":
            assert len(steady) / (t_kill - t_all - 0.5) > 10, (car, len(steady))
        # it drove, and when the server died its own stale-command stop brought the throttle to 0.0
        changes = r["throttle_changes"]
        assert any(isinstance(v, float) and v > 0 for t, v in changes if t < t_kill), (car, changes[:5])
        after = [(t - t_kill, v) for t, v in changes if t > t_kill]
        assert after and after[-1][1] == 0.0, (car, after)
        first_zero = next(t for t, v in after if v == 0.0)
        # the last command's age reaches 250 ms at most 250 ms after the kill; the next tick (50 ms, 5 ms for
        # the flooder) holds 0.0; 300 ms more for a late tick on a loaded machine
        assert first_zero < FAILSAFE_S + 0.05 + 0.3, (car, after)
    flood_sent, car1_sent = reports["flood"]["frames_sent"], reports["car1"]["frames_sent"]
    assert flood_sent > 3 * car1_sent  # it did flood
    # the car of another CA was never commanded (its throttle never left "no command")
    assert reports["car9"]["commands"] == 0 and all(v is None for _, v in reports["car9"]["throttle_changes"])


class ConstantModel:
    """A model of the pilot's frame size that answers every frame with (0.1, 0.5)."""

    pilot = types.SimpleNamespace(image_shape=(120, 160, 3))

    def infer(self, frames):
        return [(0.1, 0.5)] * len(frames)


def test_the_server_refuses_a_session_where_anyone_could_send_a_cars_frames():
    from asyncdonkey.parts.zenoh import PilotServer
    from asyncdonkey.parts.zenoh.link import ZenohConfigError, zenoh_config

    open_to_all = zenoh_config(mode="router", listen=["tcp/0.0.0.0:7447"], multicast_scouting=False)
    with pytest.raises(ZenohConfigError, match=r"listens on tcp/0.0.0.0:7447 without TLS.*steers that car"):
        PilotServer(ConstantModel(), ["car1"], config=open_to_all)  # refused before any socket is opened


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_with_the_fleet_configs_no_car_commands_or_watches_another(tmp_path):
    """In one process, each on its own session with its own certificate: the server's rules keep each car to
    its own keys (the router drops the rest before any car sees it); a view reads every car and commands none."""
    from asyncdonkey.parts.zenoh import PILOT_COMMAND, PilotServer, ZenohLink, ZenohPublisher, ZenohSubscriber
    from asyncdonkey.parts.zenoh.link import zenoh_config
    from asyncdonkey.parts.zenoh.pairing import make_fleet

    from ..waiting import await_until
    from .zenoh_loopback import free_port

    files = make_fleet(
        tmp_path, cars=["car1", "car2"], server="gpu", server_hosts=["127.0.0.1"], port=free_port(),
        listen_host="127.0.0.1", views=["base"],
    )  # fmt: skip
    server = PilotServer(ConstantModel(), ["car1", "car2"], config=zenoh_config(files.server_config))
    serving = asyncio.ensure_future(server.serve())
    car1 = ZenohLink("cars/car1", files.car_configs["car1"])
    car2 = ZenohLink("cars/car2", files.car_configs["car2"])
    view = ZenohLink("cars/car2", files.view_configs["base"])
    cmd = ["pilot/angle", "pilot/throttle"]
    try:
        cam1, cam2 = ZenohPublisher(car1, ["cam/image_array"]), ZenohPublisher(car2, ["cam/image_array"])
        sub1 = ZenohSubscriber(car1, cmd, group=PILOT_COMMAND)
        sub2 = ZenohSubscriber(car2, cmd, group=PILOT_COMMAND)
        # car1's session tries to watch car2's camera; the view does the same
        spy = ZenohSubscriber(ZenohLink("cars/car2", session=car1.session), ["cam/image_array"], ping_every_s=0)
        watcher = ZenohSubscriber(view, ["cam/image_array"], ping_every_s=0)
        frame = np.zeros((120, 160, 3), np.uint8)
        other_camera = np.zeros((60, 80, 3), np.uint8)  # car1 also sends frames of another size: dropped alone

        def drive() -> bool:
            cam1.run(other_camera, 0.0)
            cam1.run(frame, 0.0)
            cam2.run(frame, 0.0)
            return sub1.received >= 5 and sub2.received >= 5 and watcher.received >= 5

        await await_until(lambda: drive(), timeout=10)  # both cars drive on the server; the view watches car2
        assert sub1.run() == (0.1, 0.5) and sub2.run() == (0.1, 0.5)
        # the server stops answering; then car1 and the view command car2: full throttle, hard left
        server.stop()
        await serving
        await asyncio.sleep(0.3)
        taken = sub2.received
        car1_as_car2 = ZenohPublisher(ZenohLink("cars/car2", session=car1.session), cmd, group=PILOT_COMMAND)
        view_cmd = ZenohPublisher(view, cmd, group=PILOT_COMMAND)
        for _ in range(25):
            car1_as_car2.run(-1.0, 1.0, 0.0, 0.0)
            view_cmd.run(-1.0, 1.0, 0.0, 0.0)
            cam2.run(frame, 0.0)
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.3)
        assert sub2.received == taken and sub2.run() == (0.1, 0.5)  # nothing reached car2
        assert spy.received == 0  # car1 never saw car2's frames
        counters = server.counters()
        assert counters["car1"]["answered"] >= 5 and counters["car2"]["answered"] >= 5
        assert counters["car1"]["refused"] == 0 and counters["car1"]["wrong_frames"] >= 5
        assert counters["car2"]["wrong_frames"] == 0
    finally:
        if not serving.done():
            server.stop()
            await serving
        for link in (car1, car2, view):
            link.close()
        server.close()
