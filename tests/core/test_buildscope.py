"""asyncdonkey.core.buildscope: what a build() made is noted only while it runs, and closed once, actuators first."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey import Vehicle
from asyncdonkey.core.buildscope import collecting, register_close

from ..waiting import wait_until


class Recorded:
    """A part whose shutdown writes its name to ``log`` (and raises, if asked)."""

    def __init__(self, name: str, log: list[str], fail: bool = False) -> None:
        self.name, self.log, self.fail = name, log, fail

    def run(self) -> None:
        return None

    def shutdown(self) -> None:
        self.log.append(self.name)
        if self.fail:
            raise OSError(f"{self.name} would not close")


def test_vehicles_and_closes_are_noted_only_inside_the_scope_and_in_the_innermost() -> None:
    before = Vehicle()
    register_close("outside", lambda: None)
    with collecting() as outer:
        first = Vehicle()
        with collecting() as inner:
            second = Vehicle()
            register_close("inner thing", lambda: None)
        third = Vehicle()
    after = Vehicle()
    assert outer.vehicles == [first, third] and inner.vehicles == [second]
    assert [what for what, _ in inner.closes] == ["inner thing"] and outer.closes == []
    assert before not in outer.vehicles and after not in outer.vehicles  # made outside: noted nowhere


def test_close_shuts_the_actuators_down_first_then_the_rest_then_runs_the_closes_newest_first() -> None:
    log: list[str] = []
    with collecting() as scope:
        v = Vehicle()
        v.add(Recorded("camera", log))
        v.add(Recorded("throttle", log), actuator=True)
        register_close("session", lambda: log.append("session"))
        register_close("socket", lambda: log.append("socket"))
    assert scope.close() == []
    assert log == ["throttle", "camera", "socket", "session"]
    assert scope.close() == [] and len(log) == 4  # once


def test_what_fails_to_close_is_named_in_one_log_line_and_the_rest_still_closes(caplog) -> None:
    log: list[str] = []

    def broken() -> None:
        raise RuntimeError("bus gone")

    with collecting() as scope:
        v = Vehicle()
        v.add(Recorded("lidar", log, fail=True), name="lidar")
        v.add(Recorded("tub", log), name="tub")
        register_close("the I2C bus", broken)
        register_close("the session", lambda: log.append("session"))
    with caplog.at_level(logging.ERROR, logger="asyncdonkey.core.buildscope"):
        failed = scope.close()
    assert failed == ["lidar", "the I2C bus"]
    assert sorted(log) == ["lidar", "session", "tub"]
    messages = [r.getMessage() for r in caplog.records]
    assert messages == [
        "part 'lidar': shutdown() raised OSError: lidar would not close",
        "the I2C bus: closing it raised RuntimeError: bus gone",
    ]


@pytest.mark.realtime  # (the async shutdown runs on a real event loop of its own)
def test_an_async_shutdown_runs_and_a_shutdown_taking_a_timeout_gets_its_own() -> None:
    seen: dict[str, Any] = {}

    class Async:
        def run(self) -> None:
            return None

        async def shutdown(self) -> None:
            seen["async"] = True

    class Draining:
        def run(self) -> None:
            return None

        def shutdown(self, timeout: float) -> None:
            seen["timeout"] = timeout

    with collecting() as scope:
        v = Vehicle()
        v.add(Async())
        v.add(Draining(), shutdown_timeout=0.7)
    assert scope.close() == []
    assert seen == {"async": True, "timeout": 0.7}


@pytest.mark.realtime
def test_a_shutdown_that_hangs_is_abandoned_after_its_timeout() -> None:
    release = threading.Event()

    class Hangs:
        def run(self) -> None:
            return None

        def shutdown(self) -> None:
            release.wait()

    with collecting() as scope:
        v = Vehicle()
        v.add(Hangs(), shutdown_timeout=0.05)
    t0 = time.monotonic()
    try:
        assert scope.close() == ["Hangs"]
        assert time.monotonic() - t0 < 5.0  # its 0.05 s and the 0.5 s margin, on a loaded machine
    finally:
        release.set()


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.booleans()), max_size=6), st.integers(0, 3))
def test_every_part_is_shut_down_once_actuators_before_the_rest_before_the_closes(
    parts: list[tuple[bool, bool]], closes: int
) -> None:
    """For any vehicles of actuators and other parts (some failing) and any closes: each shutdown runs exactly
    once, every actuator's before any other part's of its vehicle, every part's before any close, the closes
    newest first, and exactly the failing ones are reported."""
    log: list[str] = []
    with collecting() as scope:
        v = Vehicle()
        for i, (actuator, fail) in enumerate(parts):
            v.add(Recorded(f"{'a' if actuator else 'p'}{i}", log, fail), actuator=actuator, name=f"part{i}")
        for i in range(closes):
            register_close(f"close{i}", lambda i=i: log.append(f"close{i}"))
    failed = scope.close()
    names = [f"{'a' if a else 'p'}{i}" for i, (a, _) in enumerate(parts)]
    assert sorted(log[: len(parts)]) == sorted(names)
    kinds = [name[0] for name in log[: len(parts)]]
    assert kinds == sorted(kinds)  # every "a" (actuator) before any "p"
    assert log[len(parts) :] == [f"close{i}" for i in reversed(range(closes))]
    assert sorted(failed) == sorted(f"part{i}" for i, (_, fail) in enumerate(parts) if fail)
    assert scope.close() == [] and len(log) == len(parts) + closes


@pytest.mark.network
@pytest.mark.realtime
def test_a_zenoh_link_made_in_the_scope_is_closed_with_its_threads() -> None:
    """The Zenoh case: a link opened by build() and taken by a part of its vehicle is closed, and the session's
    non-daemon callback threads (which kept a refused car's process alive) are gone."""
    pytest.importorskip("zenoh")
    from asyncdonkey.parts.zenoh import ZenohLink, ZenohPublisher

    def zenoh_threads() -> set[threading.Thread]:
        return {t for t in threading.enumerate() if "pyo3" in t.name and not t.daemon}

    before = zenoh_threads()
    with collecting() as scope:
        link = ZenohLink("cars/scope")
        v = Vehicle()
        v.add(ZenohPublisher(link, ["throttle"]), inputs=["throttle"])
        bare = ZenohLink("cars/bare")  # taken by no part
    assert zenoh_threads() - before
    assert scope.close() == []
    assert link.closed and bare.closed
    wait_until(
        lambda: not zenoh_threads() - before, 5.0, lambda: f"Zenoh's threads to end ({zenoh_threads() - before})"
    )
