import math

import pytest

from asyncdonkey import Memory


class FakeTime:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_donkeycar_api_single_and_tuple_keys():
    mem = Memory()
    mem["a"] = 1
    mem["b", "c"] = (2, 3)
    mem[["d", "e"]] = [4, 5]
    assert mem["a"] == 1
    assert mem["b", "c"] == [2, 3]
    assert mem["d"] == 4 and mem["e"] == 5
    assert mem.get(["a", "missing"]) == [1, None]
    mem.put(["x"], (9, 9))  # one key stores the value as is
    assert mem["x"] == (9, 9)
    mem.put(["y", "z"], [7, 8])
    assert (mem["y"], mem["z"]) == (7, 8)
    mem.update({"u": "v"})
    assert set(mem.keys()) == {"a", "b", "c", "d", "e", "x", "y", "z", "u"}
    assert dict(mem.items())["u"] == "v"
    assert 1 in list(mem.values())
    assert mem.d is not None and mem.d["a"] == 1


def test_put_count_mismatch_names_channels():
    mem = Memory()
    with pytest.raises(ValueError, match=r"3 channels \['a', 'b', 'c'\] but 2 values"):
        mem.put(["a", "b", "c"], (1, 2))
    with pytest.raises(ValueError, match="need a sequence of 2 values, got int"):
        mem.put(["a", "b"], 5)
    with pytest.raises(ValueError, match="2 channels"):
        mem["a", "b"] = (1, 2, 3)


def test_missing_key_raises_keyerror_like_a_dict():
    with pytest.raises(KeyError):
        Memory()["nope"]


def test_write_times_and_age():
    clock = FakeTime()
    mem = Memory(clock)
    assert mem.written_at("a") is None
    assert mem.age("a") == math.inf
    mem["a"] = 1
    clock.t = 100.25
    assert mem.written_at("a") == 100.0
    assert mem.age("a") == pytest.approx(0.25)
    mem.put(["a", "b"], (2, 3))
    assert mem.written_at("a") == mem.written_at("b") == 100.25
    assert mem.age("b", now=101.0) == pytest.approx(0.75)
