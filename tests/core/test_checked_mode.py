"""Checked mode: every part output checked against its channel's contract, a violation handled as the part's error.

Checked mode is on for this project's tests (its pytest ini says ``asyncdonkey_checked = true``; the plugin's
default is off, tests/core/test_plugin.py), so these tests say ``checked=`` wherever it matters, and one of them
looks at the default itself; off on the car.
"""

from __future__ import annotations

import asyncio
import logging
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from asyncdonkey import Contract, ContractViolation, PartError, Vehicle, get_clock
from asyncdonkey.latest import Latest

pytest_plugins = ["pytester"]


class Source:
    """Returns its values one per tick (the last one again once they run out)."""

    def __init__(self, *values) -> None:
        self.values = list(values)
        self.k = 0

    def run(self):
        v = self.values[min(self.k, len(self.values) - 1)]
        self.k += 1
        return v


class Esc:
    """An actuator: records every command it is given, and whether it was put in its safe state."""

    def __init__(self) -> None:
        self.commands: list[float] = []
        self.safe = 0

    def run(self, throttle):
        if throttle is not None:
            self.commands.append(throttle)

    def safe_state_sync(self) -> None:
        self.safe += 1

    def shutdown(self) -> None:
        self.safe_state_sync()


def car(values, *, checked: bool | None = True, on_error: str = "stop") -> tuple[Vehicle, Esc]:
    v = Vehicle(checked=checked)
    v.add(Source(*values), outputs=["throttle"], name="pilot", on_error=on_error)
    esc = Esc()
    v.add(esc, inputs=["throttle"], name="esc")
    return v, esc


# --------------------------------------------------------------------------------------------- violations
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_bad_output_stops_the_car_safely_naming_the_part_channel_value_and_contract():
    v, esc = car([0.3, 0.4, math.nan])
    with pytest.raises(PartError) as info:
        await v.run(20, 10)
    err = info.value
    assert err.part == "pilot" and err.tick == 2
    cause = err.__cause__
    assert isinstance(cause, ContractViolation)
    assert (cause.part, cause.channel, cause.reason) == ("pilot", "throttle", "nan")
    assert str(cause) == "part 'pilot' wrote channel 'throttle': got NaN (expected a finite number in [-1, 1])"
    assert esc.commands == [0.3, 0.4]  # the NaN never reached the actuator
    assert v.mem["throttle"] == 0.4  # nor Memory
    assert esc.safe >= 1 and err.report is not None and err.report.stop_reason == "error"
    assert err.report.checked and err.report.checked_parts == 1


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_value_is_shortened_in_the_message():
    v, _ = car([10**400])
    with pytest.raises(PartError) as info:
        await v.run(20, 3)
    message = str(info.value.__cause__)
    assert len(message) < 160 and "too large for a float" in message and "..." in message

    v = Vehicle(checked=True)
    v.add(Source(np.zeros((480, 640, 3), np.float32)), outputs=["cam/image_array"], name="camera")
    with pytest.raises(
        PartError, match=r"part 'camera' wrote channel 'cam/image_array': got an array of dtype float32 "
    ):
        await v.run(20, 3)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_on_error_continue_logs_and_counts_and_the_bad_value_is_not_stored(caplog):
    v, esc = car([0.3, "0.66", 0.5, 1.5, 0.2], on_error="continue")
    with caplog.at_level(logging.ERROR, logger="asyncdonkey.loop"):
        report = await v.run(20, 6)
    assert report.loops == 6 and report.part_errors == {"pilot": 2}
    assert esc.commands == [0.3, 0.3, 0.5, 0.5, 0.2, 0.2]  # each bad value: the channel kept its last good one
    logged = [r.getMessage() for r in caplog.records]
    assert any("'pilot' wrote channel 'throttle': got str '0.66', not a number" in m for m in logged)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_one_bad_output_of_several_stores_none_of_them():
    v = Vehicle(checked=True)
    v.add(Source((0.1, 0.2), (0.3, math.inf)), outputs=["angle", "throttle"], name="pilot", on_error="continue")
    report = await v.run(20, 3)
    assert report.part_errors == {"pilot": 2}
    assert (v.mem["angle"], v.mem["throttle"]) == (0.1, 0.2)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_none_and_channels_without_a_contract_pass_and_what_is_stored_is_unchanged():
    v = Vehicle(checked=True)
    zero = 0  # an int on a float channel: checked, never replaced by 0.0
    v.add(Source((zero, None, {"any": "thing"})), outputs=["throttle", "angle", "free"], name="source")
    report = await v.run(20, 2)
    assert report.part_errors == {}
    assert v.mem["throttle"] is zero and type(v.mem["throttle"]) is int
    assert v.mem["angle"] is None and v.mem["free"] == {"any": "thing"}


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_contract_declared_after_add_is_checked_and_a_part_declares_its_own():
    class Odometer:
        contracts = {"odom/speed": Contract.number(0.0, 20.0)}

        def run(self):
            return -3.0

    v = Vehicle(checked=True)
    v.add(Source(7.0), outputs=["lidar/nearest"], name="lidar")
    v.declare("lidar/nearest", Contract.number(0.0, 5.0))
    with pytest.raises(PartError, match=r"'lidar' wrote channel 'lidar/nearest': 7\.0 is outside \[0, 5\]"):
        await v.run(20, 2)

    v = Vehicle(checked=True)
    v.add(Odometer(), outputs=["odom/speed"])
    with pytest.raises(PartError, match=r"'Odometer' wrote channel 'odom/speed': -3\.0 is outside \[0, 20\]"):
        await v.run(20, 2)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_pipelined_and_pushed_outputs_are_checked_too():
    class Pilot:
        def run(self, frame):
            return math.nan, 0.0

    v = Vehicle(checked=True)
    v.add(Source(np.zeros((4, 4, 3), np.uint8)), outputs=["cam/image_array"], name="camera")
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], pipelined=True)
    with pytest.raises(PartError, match=r"'Pilot' failed in its background task: ContractViolation: .*'pilot/angle'"):
        await v.run(20, 10)
    assert "pilot/angle" not in v.mem

    class PushCamera:
        def __init__(self) -> None:
            self.frames: Latest[np.ndarray] = Latest()

        async def update(self):
            await asyncio.sleep(0.01)
            self.frames.publish(np.zeros((4, 4, 4), np.uint8), get_clock().now())  # RGBA: neither RGB nor grey
            await asyncio.sleep(3600)

        def subscribe(self, callback):
            return self.frames.subscribe(callback)

        def run(self):
            return None

    v = Vehicle(checked=True)
    v.add(PushCamera(), outputs=["cam/image_array"], name="camera")
    v.add(Esc(), inputs=["cam/image_array"], react=True, name="user")
    with pytest.raises(
        PartError,
        match=r"'camera' failed in its background task: .*got an array of shape \(4, 4, 4\) \(expected a uint8",
    ):
        await v.run(20, 10)


# ----------------------------------------------------------------------------------------- decided once
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_wrapping_is_decided_at_drive_start_only_for_entries_with_contracts_and_undone_after():
    seen = {}

    class Look:
        def run(self):
            seen["stores"] = [r.store for r in v.drive.runs]
            seen["planned"] = [e.store for e in v.parts]

    v = Vehicle(checked=True)
    v.add(Source(0.1), outputs=["throttle"], name="pilot")
    v.add(Source(1), outputs=["free"], name="free")
    v.add(Look(), name="look")
    own = [e.store for e in v.parts]
    report = await v.run(20, 1)
    assert report.checked and report.checked_parts == 1
    assert seen["stores"][0] is not own[0]  # checked: a store behind a check
    assert seen["stores"][1] is own[1] and seen["stores"][2] is None  # nothing to check: untouched
    assert seen["planned"] == own  # only the drive's runs are checked: the vehicle's entries keep their stores
    assert [e.store for e in v.parts] == own

    report = await v.run(20, 1, checked=False)
    assert not report.checked and seen["stores"] == own


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_run_overrides_the_vehicle_which_overrides_the_default():
    assert Vehicle.checked_by_default is True  # this project opts in (asyncdonkey_checked = true)
    v, _ = car([math.nan], checked=None)
    with pytest.raises(PartError):
        await v.run(20, 2)
    assert (await v.run(20, 2, checked=False)).part_errors == {}
    v, _ = car([math.nan], checked=False)
    assert not (await v.run(20, 2)).checked
    with pytest.raises(PartError):
        await v.run(20, 2, checked=True)
    with pytest.raises(ValueError, match="checked must be True, False or None"):
        Vehicle(checked=1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="checked must be True, False or None"):
        await v.run(20, 2, checked="yes")  # type: ignore[arg-type]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.asyncdonkey_checked(False)
async def test_a_test_turns_the_default_off_with_the_marker():
    assert Vehicle.checked_by_default is False
    v, esc = car([math.nan], checked=None)
    report = await v.run(20, 2)
    assert not report.checked and math.isnan(esc.commands[0])


@pytest.mark.subprocess
def test_off_by_default_on_the_car():
    code = textwrap.dedent(
        """
        import math
        from asyncdonkey import Vehicle
        from asyncdonkey.loop import run_blocking

        class Nan:
            def run(self):
                return math.nan

        v = Vehicle()
        v.add(Nan(), outputs=["throttle"])
        report = run_blocking(v.run(1000, 3), use_uvloop=False)
        print(Vehicle.checked_by_default, report.checked, report.part_errors)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.split("\n")[0] == "False False {}"


@pytest.mark.asyncdonkey_checked(False)  # as in a session that did not opt in, for the sessions run in-process
def test_the_plugin_changes_only_asyncdonkeys_default_and_puts_it_back(pytester):
    before = Vehicle.checked_by_default
    pytester.makeini("[pytest]\nasyncio_default_fixture_loop_scope = function\nasyncdonkey_checked = true\n")
    pytester.makepyfile(
        """
        import pytest
        from asyncdonkey import Vehicle

        def test_on():
            assert Vehicle.checked_by_default is True

        @pytest.mark.asyncdonkey_checked(False)
        def test_off():
            assert Vehicle.checked_by_default is False

        def test_on_again():
            assert Vehicle.checked_by_default is True
        """
    )
    pytester.runpytest().assert_outcomes(passed=3)
    assert Vehicle.checked_by_default is before

    for ini in ("", "asyncdonkey_checked = false\n"):  # not opted in, or opted out: off, and not touched
        pytester.makeini("[pytest]\nasyncio_default_fixture_loop_scope = function\n" + ini)
        pytester.makepyfile(
            """
            import pytest
            from asyncdonkey import Vehicle

            def test_off_for_the_project():
                assert Vehicle.checked_by_default is False

            @pytest.mark.asyncdonkey_checked
            def test_on_for_one_test():
                assert Vehicle.checked_by_default is True
            """
        )
        pytester.runpytest().assert_outcomes(passed=2)
        assert Vehicle.checked_by_default is before
