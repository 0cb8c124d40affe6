"""The plan ``add()`` makes: a frozen :class:`Entry`, built from one :class:`PartOptions`.

The entry is frozen so that a drive cannot write into the plan the next drive follows; the options object carries
``add()``'s arguments, and its defaults must stay ``add()``'s own (a part built through either gets the same plan).
"""

import dataclasses
import inspect

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.core.plan import Background, Entry, PartOptions, build_entry
from asyncdonkey.errors import PartSpecError
from asyncdonkey.memory import Memory


class Motor:
    def run(self, throttle):
        return None

    def safe_state_sync(self):
        pass

    def shutdown(self, timeout=None):
        pass


class Camera:
    def update(self):
        pass

    def run_threaded(self):
        return 1


def _offload(fn):
    return fn


def test_an_entry_refuses_every_write():
    v = Vehicle()
    v.add(Motor(), inputs=["throttle"], name="motor")
    e = v.parts[0]
    for field in dataclasses.fields(Entry):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(e, field.name, None)
    # per-run state has no place on it (Python 3.11's frozen slotted dataclass says so with a TypeError)
    with pytest.raises((dataclasses.FrozenInstanceError, AttributeError, TypeError)):
        e.errors = 1
    assert e.call == Motor.run.__get__(e.part)  # unchanged by the attempts


def test_entries_are_compared_by_identity():
    part = Motor()
    v = Vehicle()
    v.add(part, inputs=["throttle"])
    v.add(part, inputs=["throttle"])
    a, b = v.parts
    assert a is not b and a != b and a == a
    assert len({a, b}) == 2  # hashable though the part's fields are compared nowhere


def test_part_options_defaults_are_vehicle_add_defaults():
    add = inspect.signature(Vehicle.add).parameters
    for field in dataclasses.fields(PartOptions):
        if field.name == "name":
            continue  # add() makes it unique from the part's class name
        assert field.default == add[field.name].default, field.name


def test_build_entry_plans_from_the_options():
    mem = Memory()
    e = build_entry(mem, Motor(), PartOptions(name="motor", inputs=["throttle"], shutdown_timeout=3), _offload)
    assert (e.name, e.inputs, e.outputs, e.on_error) == ("motor", ("throttle",), (), "stop")
    assert e.actuator  # decided from safe_state_sync
    assert e.shutdown.takes_timeout and e.shutdown.timeout == 3.0
    assert e.beside.background is Background.NONE and not e.beside.pipelined
    assert e.is_sync_inline and not e.awaits

    cam = build_entry(mem, Camera(), PartOptions(name="cam", outputs=["x"], threaded=True), _offload)
    assert cam.beside.background is Background.THREAD and cam.shutdown.fn is None and not cam.actuator


@pytest.mark.parametrize(
    ("options", "says"),
    [
        ({"threaded": "yes"}, "Vehicle.add(motor): threaded must be True or False, got 'yes'"),
        ({"shutdown_timeout": 0}, "Vehicle.add(motor): shutdown_timeout must be a positive number"),
        ({"actuator": 1}, "Vehicle.add(motor): actuator must be True, False or None"),
        ({"trigger": "throttle"}, "Vehicle.add(motor): trigger='throttle' starts a pipelined part"),
    ],
)
def test_build_entry_refuses_a_wrong_option_naming_the_part(options, says):
    with pytest.raises(PartSpecError, match=says.replace("(", r"\(").replace(")", r"\)")):
        build_entry(Memory(), Motor(), PartOptions(name="motor", inputs=["throttle"], **options), _offload)
