"""Latest-value cells and their samples: sequence numbers, ages, immutability, subscribers."""

import threading

import pytest

from asyncdonkey import Latest, Sample


def test_publish_numbers_samples_and_keeps_only_the_newest():
    cell: Latest[str] = Latest()
    assert cell.sample is None and cell.value is None and cell.age(5.0) == float("inf")
    first = cell.publish("a", 1.0)
    second = cell.publish("b", 1.25)
    assert (first.value, first.timestamp, first.seq) == ("a", 1.0, 1)
    assert cell.sample is second and second == Sample("b", 1.25, 2)
    assert cell.value == "b" and cell.age(2.0) == 0.75 and second.age(2.0) == 0.75


def test_a_sample_is_immutable_and_unpacks():
    s = Latest().publish([1, 2], 3.0)
    with pytest.raises(AttributeError):
        s.value = [3]  # type: ignore[misc]
    value, timestamp, seq = s
    assert value == [1, 2] and timestamp == 3.0 and seq == 1
    assert s != Sample([1, 2], 3.0, 2)  # same value and time, another sequence number: another sample
    assert repr(s) == "Sample(value=[1, 2], timestamp=3.0, seq=1)"


def test_subscribers_see_every_publish_until_they_unsubscribe():
    cell: Latest[int] = Latest()
    seen_a: list[tuple[int, float]] = []
    seen_b: list[tuple[int, float]] = []
    stop_a = cell.subscribe(lambda v, t: seen_a.append((v, t)))
    cell.subscribe(lambda v, t: seen_b.append((v, t)))
    cell.publish(1, 0.1)
    stop_a()
    cell.publish(2, 0.2)
    assert seen_a == [(1, 0.1)] and seen_b == [(1, 0.1), (2, 0.2)]


def test_readers_in_other_threads_never_see_a_value_with_another_samples_timestamp():
    cell: Latest[int] = Latest()
    done = threading.Event()
    torn: list[Sample[int]] = []

    def read() -> None:
        while not done.is_set():
            s = cell.sample
            if s is not None and (s.timestamp != s.value * 0.5 or s.seq != s.value + 1):
                torn.append(s)

    reader = threading.Thread(target=read)
    reader.start()
    for n in range(50_000):
        cell.publish(n, n * 0.5)
    done.set()
    reader.join()
    assert torn == [] and cell.sample == Sample(49_999, 24_999.5, 50_000)
