"""Vehicle.add decides everything up front and rejects what cannot run, naming part and argument."""

import pytest

from asyncdonkey import PartSpecError, Vehicle


class Sync:
    def run(self, a=None):
        return a


class AsyncRun:
    async def run(self):
        return 1


class ThreadedNoRunThreaded:
    def update(self):
        pass

    def run(self):
        return 1


class NoRun:
    pass


class TwoInputs:
    def run(self, a, b):
        return a, b


def test_bare_string_inputs_rejected_with_hint():
    with pytest.raises(PartSpecError, match=r"Vehicle.add\(Sync\): inputs must be a list.*did you mean \['cam'\]"):
        Vehicle().add(Sync(), inputs="cam")
    with pytest.raises(PartSpecError, match=r"outputs must be a list.*'angle'"):
        Vehicle().add(Sync(), outputs="angle")


def test_non_string_channel_rejected():
    with pytest.raises(PartSpecError, match=r"inputs\[1\] must be a non-empty channel name"):
        Vehicle().add(TwoInputs(), inputs=["a", 3])


def test_threaded_must_be_bool():
    with pytest.raises(PartSpecError, match="threaded must be True or False, got 1"):
        Vehicle().add(Sync(), threaded=1)


def test_part_without_run_rejected():
    with pytest.raises(PartSpecError, match=r"Vehicle.add\(NoRun\): a part needs a run\(\) method"):
        Vehicle().add(NoRun())


def test_threaded_needs_update_and_run_threaded():
    with pytest.raises(PartSpecError, match="needs an update"):
        Vehicle().add(Sync(), threaded=True)
    with pytest.raises(PartSpecError, match="needs a run_threaded"):
        Vehicle().add(ThreadedNoRunThreaded(), threaded=True)


def test_executor_only_for_sync_run():
    with pytest.raises(PartSpecError, match="executor=True is for a sync run"):
        Vehicle().add(AsyncRun(), executor=True)


def test_arity_checked_at_add():
    with pytest.raises(PartSpecError, match=r"run\(\) cannot take the 3 input\(s\)"):
        Vehicle().add(TwoInputs(), inputs=["a", "b", "c"])
    with pytest.raises(PartSpecError, match=r"cannot take the 1 input"):
        Vehicle().add(TwoInputs(), inputs=["a"])


def test_age_suffix_not_allowed_on_outputs():
    with pytest.raises(PartSpecError, match="'x@age' ends in '@age'"):
        Vehicle().add(Sync(), outputs=["x@age"])


def test_bad_on_error_and_run_condition():
    with pytest.raises(PartSpecError, match="on_error must be 'stop' or 'continue'"):
        Vehicle().add(Sync(), on_error="ignore")
    with pytest.raises(PartSpecError, match="run_condition must be a channel name"):
        Vehicle().add(Sync(), run_condition=["run_pilot"])


def test_names_made_unique_and_explicit_names_used():
    v = Vehicle()
    v.add(Sync())
    v.add(Sync())
    v.add(Sync(), name="pilot")
    assert [e.name for e in v.parts] == ["Sync", "Sync#2", "pilot"]
