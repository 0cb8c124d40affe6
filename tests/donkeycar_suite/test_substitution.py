"""The Donkeycar suite beside this file really runs on asyncdonkey's classes, and all of it is collected."""

import importlib
import inspect

import donkeycar
import donkeycar.memory
import donkeycar.vehicle
import pytest

import asyncdonkey
from asyncdonkey.commands.donkey import donkeycar_replaced

SUITE = ("test_vehicle", "test_memory", "test_kinematics")


@pytest.mark.donkeycar
def test_donkeycar_names_are_asyncdonkeys_while_the_tests_run():
    assert donkeycar.Vehicle is donkeycar.vehicle.Vehicle is asyncdonkey.Vehicle
    assert donkeycar.Memory is donkeycar.memory.Memory is asyncdonkey.Memory
    # bound when Donkeycar's test modules were imported by the wrappers
    assert importlib.import_module("donkeycar.tests.test_kinematics").Vehicle is asyncdonkey.Vehicle
    assert importlib.import_module("donkeycar.tests.test_memory").Memory is asyncdonkey.Memory


@pytest.mark.donkeycar
def test_the_replaced_names_are_restored_on_exit():
    class OtherVehicle(asyncdonkey.Vehicle):
        pass

    class OtherMemory(asyncdonkey.Memory):
        pass

    before = (donkeycar.Vehicle, donkeycar.vehicle.Vehicle, donkeycar.Memory, donkeycar.memory.Memory)
    with donkeycar_replaced(OtherVehicle, OtherMemory):
        assert donkeycar.Vehicle is donkeycar.vehicle.Vehicle is OtherVehicle
        assert donkeycar.Memory is donkeycar.memory.Memory is OtherMemory
    assert (donkeycar.Vehicle, donkeycar.vehicle.Vehicle, donkeycar.Memory, donkeycar.memory.Memory) == before


def _tests_in(module) -> set[str]:
    return {
        name
        for name, obj in vars(module).items()
        if (name.startswith("test") and inspect.isfunction(obj)) or (name.startswith("Test") and inspect.isclass(obj))
    }


@pytest.mark.parametrize("name", SUITE)
def test_every_donkeycar_test_is_collected(name):
    theirs = _tests_in(importlib.import_module(f"donkeycar.tests.{name}"))
    assert theirs, f"no tests found in donkeycar.tests.{name}"
    # the wrapper beside this file, in the same package
    wrapper = importlib.import_module(f".test_donkeycar_{name.removeprefix('test_')}", __package__)
    assert theirs <= _tests_in(wrapper), f"missing from {wrapper.__name__}: {sorted(theirs - _tests_in(wrapper))}"
