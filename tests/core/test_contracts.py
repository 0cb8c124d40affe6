"""Channel contracts: each class of bad value refused with its reason, good values normalised, gates counting."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from asyncdonkey import REFUSED, Contract, Contracts, ContractViolation, Vehicle
from asyncdonkey.contracts import Kind, default_contracts

HUGE = 10**400  # float(HUGE) raises OverflowError


@pytest.mark.parametrize(
    ("value", "reason"),
    [
        (math.nan, "nan"),
        (math.inf, "inf"),
        (-math.inf, "inf"),
        (HUGE, "range"),
        (1.5, "range"),
        (-1.0001, "range"),
        ("0.66", "type"),
        ("full", "type"),
        ([0.5], "type"),
        (list(range(500_000)), "type"),
        (np.array(math.nan), "type"),  # a 0-d array is not a number
        (True, "type"),
        ({"throttle": 0.5}, "type"),
        (b"0.5", "type"),
    ],
)
def test_a_command_channel_refuses_each_class_of_bad_value_with_its_reason(value, reason):
    c = Contracts().get("throttle")
    assert c is not None
    with pytest.raises(ContractViolation) as info:
        c.check(value)
    assert info.value.reason == reason
    assert len(str(info.value)) < 200  # a 400-digit integer or a 500,000-item list is never printed whole


@pytest.mark.parametrize(
    ("value", "stored"),
    [(0.5, 0.5), (1, 1.0), (-1, -1.0), (np.float32(0.25), 0.25), (np.int64(0), 0.0), (-0.0, 0.0)],
)
def test_good_numbers_are_stored_as_python_floats(value, stored):
    out = Contracts().check("throttle", value)
    assert out == stored and type(out) is float


@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**500), 10**500)))
def test_whatever_a_number_contract_admits_is_a_finite_float_in_range(value):
    c = Contract.number(-1.0, 1.0)
    try:
        out = c.check(value)
    except ContractViolation:
        return
    assert type(out) is float and math.isfinite(out) and -1.0 <= out <= 1.0


def test_the_mode_recording_and_image_defaults():
    cs = Contracts()
    assert cs.check("user/mode", "local") == "local"
    for bad, reason in (("autopilot", "choice"), (1, "type"), ("", "choice")):
        with pytest.raises(ContractViolation) as info:
            cs.check("user/mode", bad)
        assert info.value.reason == reason
    assert cs.check("recording", np.bool_(True)) is True
    with pytest.raises(ContractViolation):
        cs.check("recording", 1)
    frame = np.zeros((120, 160, 3), np.uint8)
    assert cs.check("cam/image_array", frame) is frame
    grey = np.zeros((120, 160), np.uint8)  # Donkeycar's cameras with IMAGE_DEPTH = 1
    assert cs.check("cam/image_array", grey) is grey
    for bad, reason in (
        (frame.astype(np.float32), "dtype"),
        (np.zeros((120, 160, 1), np.uint8), "shape"),
        (np.zeros((120, 160, 4), np.uint8), "shape"),
        (np.zeros((5000, 5000, 3), np.uint8), "size"),
        (frame.tolist(), "type"),
    ):
        with pytest.raises(ContractViolation) as info:
            cs.check("cam/image_array", bad)
        assert info.value.reason == reason
    assert {k: c.safe for k, c in default_contracts().items() if c.safe is not None} == {
        "user/angle": 0.0,
        "user/throttle": 0.0,
        "pilot/angle": 0.0,
        "pilot/throttle": 0.0,
        "angle": 0.0,
        "throttle": 0.0,
        "user/mode": "user",
        "recording": False,
    }


def test_other_kinds():
    assert Contract.integer(0, 10).check(np.int16(3)) == 3
    with pytest.raises(ContractViolation):
        Contract.integer(0, 10).check(11)
    with pytest.raises(ContractViolation):
        Contract.integer(0, 10).check(2.0)
    jpeg = Contract.jpeg(100)
    assert jpeg.check(bytearray(b"\xff\xd8abc\xff\xd9")) == b"\xff\xd8abc\xff\xd9"
    for bad, reason in ((b"\x89PNG....", "encoding"), (b"\xff\xd8" + b"x" * 200 + b"\xff\xd9", "size"), ("s", "type")):
        with pytest.raises(ContractViolation) as info:
            jpeg.check(bad)
        assert info.value.reason == reason
    assert Contract.blob(4).check(b"abcd") == b"abcd"
    with pytest.raises(ContractViolation):
        Contract.array(np.float32, (3,)).check(np.array([1.0, math.nan, 2.0], np.float32))
    assert Contract.array(np.float32).kind is Kind.ARRAY


def test_a_contract_whose_safe_value_breaks_it_is_refused_when_made():
    with pytest.raises(ContractViolation):
        Contract.number(-1, 1, safe=2.0)
    with pytest.raises(ContractViolation):
        Contract.choice("a", "b", safe="c")
    with pytest.raises(ValueError, match="strings"):
        Contract.choice()


def test_a_gate_refuses_counts_per_channel_and_reason_and_logs_rate_limited(caplog):
    caplog.set_level(logging.WARNING, "asyncdonkey.contracts")
    gate = Contracts().gate("test boundary")
    assert gate.admit("throttle", 0.5) == 0.5
    assert gate.admit("unknown/channel", "anything") == "anything"  # no contract, no check
    for now, bad in enumerate((math.nan, math.nan, HUGE, "0.66", None)):
        assert gate.admit("throttle", bad, now=now * 0.1) is REFUSED
    assert gate.counts() == {"throttle": {"nan": 2, "range": 1, "type": 1, "empty": 1}}
    assert gate.total_refused == 5
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 4  # the second NaN within the interval is held back
    assert messages[0].startswith("test boundary: refused a value for 'throttle': got NaN")
    assert "expected a finite number in [-1, 1]" in messages[0]
    assert not REFUSED


def test_a_vehicle_takes_declarations_from_itself_and_from_its_parts():
    class Imu:
        contracts = {"imu/acl_x": Contract.number(-160, 160)}

        def run(self):
            return 0.0

    class Receiver:
        def __init__(self):
            self.contracts_seen = None

        def use_contracts(self, contracts):
            self.contracts_seen = contracts

        def run(self):
            return None

    v = Vehicle(contracts={"odom/speed": Contract.number(0, 20)})
    v.declare("throttle", Contract.number(-0.5, 0.5, safe=0.0))
    receiver = Receiver()
    v.add(Imu(), outputs=["imu/acl_x"])
    v.add(receiver, outputs=["pilot/throttle"])
    assert receiver.contracts_seen is v.contracts
    assert v.contracts.get("imu/acl_x") == Contract.number(-160, 160)
    with pytest.raises(ContractViolation, match="odom/speed"):
        v.contracts.check("odom/speed", -1.0)
    with pytest.raises(ContractViolation):
        v.contracts.check("throttle", 0.6)  # the declaration replaced the default
    assert v.contracts.check("user/throttle", 1.0) == 1.0  # the defaults are still there
