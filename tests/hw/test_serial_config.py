"""SerialConfig: a serial port's settings in one frozen object, built from the keyword form or given whole; the
line queue the port reads into."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.hw.serial_config import SERIAL_SETTINGS, SerialConfig
from asyncdonkey.hw.serial_port import LineQueue, SerialCounters, SerialPort


def test_the_keyword_form_and_the_config_form_make_the_same_port():
    by_keywords = SerialPort("/dev/ttyACM0", 9600, skip_first_line=True, max_line_length=64, name="encoder")
    config = SerialConfig("/dev/ttyACM0", 9600, skip_first_line=True, max_line_length=64, name="encoder")
    given_config = SerialPort(config)
    assert by_keywords.config == given_config.config == config
    assert given_config.config is config
    assert (given_config.port, given_config.baudrate, given_config.max_line_length) == ("/dev/ttyACM0", 9600, 64)
    assert given_config.name == "encoder" and SerialPort("/dev/ttyUSB1").name == "/dev/ttyUSB1"
    assert SerialPort(port="/dev/ttyUSB1", baudrate=57600).config == SerialConfig("/dev/ttyUSB1", 57600)


def test_one_config_serves_several_ports_varied_by_keywords():
    shared = SerialConfig("/dev/serial/by-id/a", 115200, max_lines=16, backoff_initial_s=0.1)
    a = SerialPort(shared)
    b = SerialPort(shared, port="/dev/serial/by-id/b", max_lines=32)
    assert b.config == dataclasses.replace(shared, port="/dev/serial/by-id/b", max_lines=32)
    assert (a.port, a.max_lines, b.port, b.max_lines) == ("/dev/serial/by-id/a", 16, "/dev/serial/by-id/b", 32)
    assert b.backoff_initial_s == 0.1
    with pytest.raises(dataclasses.FrozenInstanceError):
        shared.baudrate = 9600  # type: ignore[misc]
    with pytest.raises(ValueError, match="max_lines"):
        SerialPort(shared, max_lines=0)


@pytest.mark.parametrize(
    ("bad", "named"),
    [
        ({"port": ""}, "port"),
        ({"baudrate": 0}, "baudrate"),
        ({"baudrate": 9600.0}, "baudrate"),
        ({"parity": "X"}, "parity"),
        ({"bytesize": 9}, "bytesize"),
        ({"stopbits": 3}, "stopbits"),
        ({"max_lines": 0}, "max_lines"),
        ({"max_line_length": -1}, "max_line_length"),
        ({"backoff_initial_s": 0}, "backoff_initial_s"),
        ({"backoff_initial_s": 3.0, "backoff_max_s": 2.0}, "backoff_max_s"),
    ],
)
def test_each_bad_setting_is_refused_naming_the_port_and_the_setting(bad, named):
    base = {"port": "/dev/ttyACM0", "name": "gps"}
    with pytest.raises(ValueError, match=rf"SerialPort\('gps'\): .*{named}"):
        SerialConfig(**{**base, **bad})
    with pytest.raises(ValueError, match=named):
        SerialPort(**{**base, **bad})


def test_an_unknown_encoding_or_setting_fails_at_once():
    with pytest.raises(LookupError):
        SerialConfig("/dev/ttyACM0", encoding="no-such-codec")
    with pytest.raises(TypeError, match="'baud'"):
        SerialPort("/dev/ttyACM0", baud=9600)


def test_counters_read_as_attributes_and_the_port_keeps_its_state_in_small_objects():
    port = SerialPort("/dev/ttyACM0")
    port.counters.connects = 3
    port.counters.writes_dropped = 2
    assert (port.connects, port.writes_dropped) == (3, 2)
    assert {k: v for k, v in port.stats().items() if v} == {"connects": 3, "writes_dropped": 2}
    assert set(port.stats()) >= {f.name for f in dataclasses.fields(SerialCounters)}
    assert len(vars(port)) <= 20, sorted(vars(port))
    assert "port" in SERIAL_SETTINGS and "receiver" not in SERIAL_SETTINGS  # wiring is not a setting


@settings(max_examples=150, deadline=None)
@given(
    max_lines=st.integers(min_value=1, max_value=8),
    skip=st.booleans(),
    chunks=st.lists(st.lists(st.sampled_from(["a", "bb", "12,34", ""]), max_size=6), max_size=12),
)
def test_the_line_queue_stays_bounded_and_accounts_for_every_line(max_lines, skip, chunks):
    """Every complete line is queued, dropped as the oldest when full, or skipped as the first after a connect:
    none is lost uncounted, and the queue never holds more than ``max_lines``."""
    queue = LineQueue(SerialConfig("/dev/null", max_lines=max_lines, skip_first_line=skip))
    counts = SerialCounters()
    queue.reconnected()
    sent: list[str] = []
    for chunk in chunks:
        queue.feed(b"".join(t.encode() + b"\r\n" for t in chunk), lambda: 1.0, counts)
        sent += [t for t in chunk if t]  # empty lines are skipped by the framer, never counted
        assert len(queue.lines) <= max_lines
    skipped = 1 if skip and sent else 0
    assert counts.first_lines_skipped == skipped
    assert counts.lines_received == len(sent) - skipped
    assert counts.lines_received == counts.lines_dropped + len(queue.lines)
    assert [line.text for line in queue.lines] == sent[skipped:][-max_lines:]  # the newest, in order
