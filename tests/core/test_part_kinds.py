"""Every kind of part the drive loop supports, each decided once at add()."""

import asyncio
import math
import threading
import time

import pytest

from asyncdonkey import OutputCountError, PartError, Poller, Vehicle, get_clock


class Source:
    def __init__(self, values):
        self.values = iter(values)

    def run(self):
        return next(self.values)


class Collect:
    def __init__(self) -> None:
        self.seen = []

    def run(self, *args):
        self.seen.append(args)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_sync_and_async_parts_run_in_order_and_pass_values():
    order = []

    class A:
        def run(self):
            order.append("a")
            return 1, 2

    class B:
        async def run(self, x, y):
            order.append("b")
            await asyncio.sleep(0.001)
            return x + y

    class C:
        def run(self, s):
            order.append("c")
            return s * 10

    v = Vehicle()
    v.add(A(), outputs=["x", "y"])
    v.add(B(), inputs=["x", "y"], outputs=["s"])
    v.add(C(), inputs=["s"], outputs=["t"])
    await v.run(20, 2)
    assert order == ["a", "b", "c"] * 2
    assert v.mem["t"] == 30


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_none_writes_nothing_and_one_output_stores_tuple_as_is():
    v = Vehicle()
    v.mem["keep"] = "old"
    v.add(Source([None, None]), outputs=["keep"])
    v.add(Source([(1, 2), (3, 4)]), outputs=["pair"])
    await v.run(20, 2)
    assert v.mem["keep"] == "old"
    assert v.mem["pair"] == (3, 4)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_output_count_mismatch_names_part_and_channels():
    v = Vehicle()
    v.add(Source([(1, 2)]), outputs=["a", "b", "c"], name="pilot")
    with pytest.raises(
        PartError,
        match=r"part 'pilot' failed on tick 0: OutputCountError: returned 2 values "
        r"for 3 outputs \['a', 'b', 'c'\]",
    ) as info:
        await v.run(20, 5)
    assert isinstance(info.value.__cause__, OutputCountError)
    v2 = Vehicle()
    v2.add(Source([7]), outputs=["a", "b"])
    with pytest.raises(PartError, match="returned int for 2 outputs"):
        await v2.run(20, 1)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_run_condition_skips_part():
    ran = Collect()
    v = Vehicle()
    v.add(Source([True, False, 1, 0, None]), outputs=["go"])
    v.add(Source(range(5)), outputs=["i"])
    v.add(ran, inputs=["i"], run_condition="go")
    await v.run(20, 5)
    assert ran.seen == [(0,), (2,)]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.asyncdonkey_checked(False)  # 2.0 is only a value unlike the first, outside a throttle's [-1, 1]
async def test_age_inputs_measure_staleness_on_the_runtime_clock():
    ages = Collect()
    v = Vehicle()
    v.add(Source([1.0, None, None, 2.0, None]), outputs=["throttle"])  # stops publishing for two ticks
    v.add(ages, inputs=["throttle", "throttle@age", "never@age"])
    await v.run(10, 5)
    vals = [a[0] for a in ages.seen]
    got = [a[1] for a in ages.seen]
    assert vals == [1.0, 1.0, 1.0, 2.0, 2.0]
    assert got == pytest.approx([0.0, 0.1, 0.2, 0.0, 0.1], abs=1e-9)
    assert all(math.isinf(a[2]) for a in ages.seen)


class DonkeyThreaded:
    """A Donkeycar-style threaded part: blocking update() loop, run_threaded() returns the latest value."""

    def __init__(self) -> None:
        self.on = True
        self.value = 0
        self.thread_name = None
        self.started = threading.Event()

    def update(self):
        self.thread_name = threading.current_thread().name
        while self.on:
            self.value += 1
            self.started.set()
            time.sleep(0.001)

    def run_threaded(self, scale):
        return self.value * scale

    def shutdown(self):
        self.on = False


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_donkeycar_threaded_part_runs_in_its_own_thread_and_ends_at_shutdown():
    part = DonkeyThreaded()
    v = Vehicle()
    v.mem["scale"] = 2
    v.add(part, inputs=["scale"], outputs=["out"], threaded=True)
    await v.run(100, 20)
    assert part.thread_name == "part:DonkeyThreaded"
    assert v.mem["out"] > 0 and v.mem["out"] % 2 == 0
    assert not any(t.name == "part:DonkeyThreaded" for t in threading.enumerate())


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_threaded_update_that_returns_at_once_is_fine():
    class Quick:
        def update(self):
            return

        def run_threaded(self):
            return 5

    v = Vehicle()
    v.add(Quick(), outputs=["q"], threaded=True)
    await v.run(20, 3)
    assert v.mem["q"] == 5


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_async_update_runs_as_background_task_and_is_cancelled():
    class Ticker:
        def __init__(self) -> None:
            self.count = 0
            self.cancelled = False

        async def update(self):
            clock = get_clock()
            try:
                while True:
                    await clock.sleep_until((self.count + 1) * 0.03)  # 33.3 Hz beside a 10 Hz loop
                    self.count += 1
            except asyncio.CancelledError:
                self.cancelled = True
                raise

        def run(self):
            return self.count

    t = Ticker()
    v = Vehicle()
    v.add(t, outputs=["count"])
    await v.run(10, 11)
    assert v.mem["count"] == 33  # exactly: the 11th tick (t = 1.0 s) sees the update at 0.99 s
    assert t.cancelled


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_executor_offload_runs_off_the_loop_thread_in_order():
    loop_thread = threading.get_ident()
    seen = []

    class Heavy:
        def run(self, x):
            seen.append(threading.get_ident())
            time.sleep(0.02)  # real blocking work
            return x + 1

    v = Vehicle()
    v.add(Source(range(5)), outputs=["x"])
    v.add(Heavy(), inputs=["x"], outputs=["y"], executor=True)
    v.add(Collect(), inputs=["y"])
    await v.run(20, 5)
    assert v.mem["y"] == 5
    assert all(ident != loop_thread for ident in seen)
    # blocking work in a thread costs no virtual time: the ticks stay on their deadlines
    assert v.profiler.lateness.max == pytest.approx(0.0, abs=1e-9)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_poller_publishes_latest_value_with_timestamp_and_sequence():
    reads = []

    def read():
        reads.append(threading.current_thread().name)
        return len(reads)

    poller = Poller(read, rate_hz=60, name="imu")
    v = Vehicle()
    v.add(poller, outputs=["imu"])
    await v.run(20, 21)  # 1 s
    assert v.mem["imu"] in (60, 61)
    s = poller.sample
    assert s is not None and s.seq == poller.reads and s.value == poller.reads
    assert s.timestamp == pytest.approx((s.seq - 1) / 60, abs=1e-9)
    assert all(name.startswith("poll:imu") for name in reads)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_poller_counts_read_errors_and_keeps_polling():
    n = {"i": 0}

    def flaky():
        n["i"] += 1
        if n["i"] % 3 == 0:
            raise OSError(121, "Remote I/O error")
        return n["i"]

    poller = Poller(flaky, rate_hz=30)
    v = Vehicle()
    v.add(poller, outputs=["v"])
    await v.run(10, 11)
    # 1 s at 30 Hz: 30 reads, or 31 when the read due at exactly 1.0 s beats the shutdown; every third failed
    assert poller.errors == 10 and poller.reads in (20, 21)
    assert isinstance(poller.last_error, OSError)
