"""Drive modes, the pilot condition and recording on throttle, alone and wired into a Vehicle."""

import ast
import asyncio
import math
from pathlib import Path

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.control import (
    DRIVE_MODES,
    AutoRecordOnThrottle,
    DriveMode,
    PilotCondition,
    normalise_mode,
)


@pytest.mark.parametrize(
    ("mode", "expected"),
    [
        ("user", (0.3, 0.4)),
        ("local_angle", (-0.5, 0.4)),
        ("local", (-0.5, 0.35)),
        ("local_pilot", (-0.5, 0.35)),
    ],
)
def test_drive_mode_picks_the_command(mode, expected):
    got = DriveMode(ai_throttle_mult=0.5).run(mode, 0.3, 0.4, -0.5, 0.7)
    assert got == pytest.approx(expected)


def test_no_mode_yet_means_the_user_drives():
    assert DriveMode().run(None, 0.1, 0.2, 0.9, 0.9) == (0.1, 0.2)
    assert PilotCondition().run(None) is False


def test_missing_or_nan_pilot_values_are_neutral():
    dm = DriveMode(ai_throttle_mult=2.0)
    assert dm.run("local", 0.1, 0.2, None, None) == (0.0, 0.0)
    assert dm.run("local", 0.1, 0.2, math.nan, math.nan) == (0.0, 0.0)
    assert dm.run("local_angle", 0.1, 0.2, None, 0.9) == (0.0, 0.2)


def test_unknown_mode_fails_loudly_instead_of_handing_over_to_the_pilot():
    with pytest.raises(ValueError, match=r"DriveMode: unknown mode 'autopilot'.*user, local_angle, local"):
        DriveMode().run("autopilot", 0.0, 0.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="PilotCondition"):
        PilotCondition().run(3)
    with pytest.raises(ValueError, match="ai_throttle_mult"):
        DriveMode(ai_throttle_mult=-1)


@pytest.mark.donkeycar
def test_modes_cycle_in_donkeycar_order_and_aliases_normalise():
    assert DRIVE_MODES == ("user", "local_angle", "local")
    assert normalise_mode("local_pilot") == "local"
    assert [PilotCondition().run(m) for m in DRIVE_MODES] == [False, True, True]
    theirs = _donkeycar_template_class("basic.py", "PilotCondition")()
    assert [theirs.run(m) for m in DRIVE_MODES] == [False, True, True]


def _donkeycar_template_class(template: str, name: str) -> type:
    """Donkeycar defines its drive-mode parts inside its car templates, whose imports pull in a web stack;
    compile just the one class from the installed template (make test installs donkeycar)."""
    import donkeycar

    path = Path(donkeycar.__file__).parent / "templates" / template
    tree = ast.parse(path.read_text(), str(path))
    node = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == name)
    namespace: dict = {}
    exec(compile(ast.Module([node], type_ignores=[]), str(path), "exec"), namespace)
    return namespace[name]


@pytest.mark.donkeycar
def test_same_results_as_donkeycars_drive_mode_on_its_modes():
    theirs = _donkeycar_template_class("complete.py", "DriveMode")(ai_throttle_mult=0.8)
    ours = DriveMode(ai_throttle_mult=0.8)
    for mode in ("user", "local_angle", "local_pilot", "local"):
        for pa, pt in [(0.25, 0.5), (None, None), (-1.0, 1.0), (0.0, 0.3)]:
            assert ours.run(mode, -0.2, 0.6, pa, pt) == pytest.approx(theirs.run(mode, -0.2, 0.6, pa, pt))


def test_auto_record_only_while_the_user_has_the_throttle_open():
    rec = AutoRecordOnThrottle(dead_zone=0.05)
    assert rec.run("user", 0.3) is True
    assert rec.run("user", -0.3) is True  # reversing is driving too
    assert rec.run("user", 0.04) is False  # inside the dead zone
    assert rec.run("user", None) is False
    assert rec.run("local", 0.5) is False  # the pilot drives: nothing to learn from
    assert rec.run("local_angle", 0.5) is False


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_recording_holds_after_the_throttle_closes_on_runtime_time():
    loop = asyncio.get_running_loop()
    rec = AutoRecordOnThrottle(hold_s=0.5)
    t0 = loop.time()
    assert rec.run("user", 0.4) is True
    await asyncio.sleep(0.3)
    assert rec.run("user", 0.0) is True  # 0.3 s after lift-off: still held
    await asyncio.sleep(0.25)
    assert loop.time() - t0 == pytest.approx(0.55)
    assert rec.run("user", 0.0) is False  # 0.55 s: the hold is over
    assert rec.run("user", 0.2) is True
    assert rec.run("local", 0.0) is False  # leaving user mode ends the hold at once
    assert rec.run("user", 0.0) is False


class Script:
    """A controller replaying (mode, angle, throttle) per tick."""

    def __init__(self, rows):
        self.rows = iter(rows)

    def run(self):
        return next(self.rows)


class CountingPilot:
    def __init__(self):
        self.calls = 0

    def run(self, _image):
        self.calls += 1
        return -0.5, 0.6


class Sink:
    def __init__(self):
        self.seen = []

    def run(self, angle, throttle, recording):
        self.seen.append((angle, throttle, recording))


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_wired_in_a_vehicle_the_pilot_runs_only_when_it_drives():
    rows = [("user", 0.1, 0.3), ("local_angle", 0.1, 0.3), ("local", 0.1, 0.3), ("user", 0.2, 0.0)]
    pilot, sink = CountingPilot(), Sink()
    v = Vehicle()
    v.add(Script(rows), outputs=["user/mode", "user/angle", "user/throttle"])
    v.add(PilotCondition(), inputs=["user/mode"], outputs=["run_pilot"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], run_condition="run_pilot")
    v.add(
        DriveMode(ai_throttle_mult=0.5),
        inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
        outputs=["angle", "throttle"],
    )
    v.add(AutoRecordOnThrottle(), inputs=["user/mode", "user/throttle"], outputs=["recording"])
    v.add(sink, inputs=["angle", "throttle", "recording"])
    await v.run(rate_hz=20, max_loop_count=len(rows))
    assert pilot.calls == 2
    assert sink.seen == [
        (0.1, 0.3, True),
        (-0.5, 0.3, False),
        (-0.5, pytest.approx(0.3), False),
        (0.2, 0.0, False),
    ]
