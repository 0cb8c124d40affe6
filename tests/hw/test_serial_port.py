"""SerialPort against pseudo-terminal peers: framing, bounded buffers, exact writes, unplug/replug, backoff.

Real-pty tests run on the real asyncio loop and on uvloop with short timeouts; the reconnect schedule is
checked exactly on the virtual clock.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Awaitable, Callable

import pytest
import uvloop
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.clock import get_clock
from asyncdonkey.hw.serial_port import LineFramer, SerialPort, SerialPortClosed
from asyncdonkey.testing import VirtualClockLoop
from asyncdonkey.testing.serial_peers import LinePeer, PtyPeer

from ..waiting import await_until

LOOPS = [
    pytest.param(asyncio.SelectorEventLoop, id="asyncio"),
    pytest.param(uvloop.new_event_loop, id="uvloop"),
]


def run_on(loop_factory: Callable[[], asyncio.AbstractEventLoop], coro: Awaitable[None]) -> None:
    with asyncio.Runner(loop_factory=loop_factory) as runner:
        runner.run(coro)  # type: ignore[arg-type]


async def until(cond: Callable[[], bool], timeout: float = 0.5) -> None:
    """:func:`await_until` with this file's step: on the virtual clock a bare yield between checks, since a sleep
    there would move virtual time past the device's answer."""
    await await_until(cond, timeout, step=0 if get_clock().is_virtual else 0.001)


class Echo(LinePeer):
    """A device that answers each command line with ``ok:<command>``."""

    def line_received(self, text: str) -> None:
        self.send(f"ok:{text}\r\n".encode())


# ---------------------------------------------------------------------------------------------- framing
def test_framer_splits_lines_strips_cr_and_skips_empty():
    f = LineFramer(max_line_length=16)
    assert f.feed(b"12,34\r\n\r\n5") == ["12,34"]
    assert f.feed(b"6,78\n") == ["56,78"]
    assert f.feed(b"a\rb\r\n") == ["a\rb"]  # only the CR of the line ending goes


def test_framer_drops_overlong_lines_without_buffering_them():
    f = LineFramer(max_line_length=8)
    assert f.feed(b"ok\n" + b"x" * 100) == ["ok"]
    assert len(f._buf) == 0  # the garbage was not kept
    assert f.feed(b"yyy\nfine\n") == ["fine"]  # the tail of the overlong line goes too
    assert f.overlong == 1
    assert f.feed(b"123456789\n12345678\n") == ["12345678"]  # 9 bytes: over; 8: at the limit
    assert f.overlong == 2


def test_framer_counts_undecodable_lines():
    f = LineFramer(encoding="ascii")
    assert f.feed(b"\xff\xfe\nok\n") == ["ok"]
    assert f.decode_errors == 1


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.binary(max_size=40).filter(lambda b: b"\n" not in b and b"\r" not in b), max_size=20),
    st.lists(st.integers(min_value=1, max_value=30), min_size=1, max_size=30),
)
def test_framer_result_does_not_depend_on_how_bytes_are_chunked(lines, cuts):
    stream = b"".join(line + b"\r\n" for line in lines)
    whole = LineFramer(max_line_length=32, encoding="latin-1")
    expected = whole.feed(stream)
    chunked = LineFramer(max_line_length=32, encoding="latin-1")
    got, i, k = [], 0, 0
    while i < len(stream):
        step = cuts[k % len(cuts)]
        got += chunked.feed(stream[i : i + step])
        i += step
        k += 1
    assert got == expected
    assert chunked.overlong == whole.overlong
    assert expected == [ln.decode("latin-1") for ln in lines if 0 < len(ln) <= 32]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(max_size=200), max_size=20))
def test_framer_never_raises_and_stays_bounded_on_garbage(chunks):
    f = LineFramer(max_line_length=24)
    for c in chunks:
        for line in f.feed(c):
            assert 0 < len(line) <= 24
        assert len(f._buf) <= 25


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="baudrate"):
        SerialPort("/dev/null", 0)
    with pytest.raises(ValueError, match="parity"):
        SerialPort("/dev/null", parity="X")
    with pytest.raises(TypeError, match="data_received"):
        SerialPort("/dev/null", receiver=object())  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------ real pty io
@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_lines_in_exact_bytes_out(loop_factory):
    async def body():
        with Echo() as peer:
            async with SerialPort(peer.path, 115200) as port:
                await asyncio.wait_for(port.wait_connected(), 1)
                assert port.writeln("c16")
                assert port.write(b"p\n")
                first = await asyncio.wait_for(port.readline(), 0.5)
                second = await asyncio.wait_for(port.readline(), 0.5)
                assert (first.text, second.text) == ("ok:c16", "ok:p")
                assert first.timestamp <= second.timestamp <= get_clock().now()
                assert bytes(peer.received) == b"c16\np\n"
                assert port.bytes_written == 6
            with pytest.raises(SerialPortClosed):
                await port.readline()

    run_on(loop_factory, body())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_line_buffer_is_bounded_and_drops_the_oldest(loop_factory):
    async def body():
        with PtyPeer("flood") as peer:
            async with SerialPort(peer.path, max_lines=50) as port:
                await asyncio.wait_for(port.wait_connected(), 1)
                peer.send(b"".join(b"line %d\r\n" % i for i in range(300)))
                await until(lambda: port.lines_received == 300)
                assert port.lines_buffered == 50
                assert port.lines_dropped == 250
                assert [ln.text for ln in port.drain()] == [f"line {i}" for i in range(250, 300)]
                assert port.get_line_nowait() is None

    run_on(loop_factory, body())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_overlong_garbage_is_dropped_and_counted(loop_factory):
    async def body():
        with PtyPeer("noise") as peer:
            async with SerialPort(peer.path, max_line_length=20) as port:
                await asyncio.wait_for(port.wait_connected(), 1)
                peer.send(b"a" * 5000 + b"\r\nafter\r\n")
                line = await asyncio.wait_for(port.readline(), 0.5)
                assert line.text == "after"
                assert port.overlong_dropped == 1

    run_on(loop_factory, body())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_unplug_and_replug_reconnects_to_the_same_path(loop_factory):
    async def body():
        hooks = []
        with Echo("arduino") as peer:
            port = SerialPort(
                peer.path, backoff_initial_s=0.02, on_connect=lambda p: hooks.append(p.connects) or p.writeln("hello")
            )
            await port.start()
            await asyncio.wait_for(port.wait_connected(), 1)
            assert (await asyncio.wait_for(port.readline(), 0.5)).text == "ok:hello"
            first_tty = peer.tty_path

            peer.unplug()
            await until(lambda: not port.connected)
            assert port.disconnects == 1
            assert not port.writeln("lost")  # refused and counted, not buffered for a device that is gone
            assert port.writes_dropped == 1
            await until(lambda: port.open_failures >= 2)  # it keeps trying the path

            peer.plug()
            assert peer.tty_path != first_tty or peer.plugs == 2
            await asyncio.wait_for(port.wait_connected(), 1)
            assert (await asyncio.wait_for(port.readline(), 0.5)).text == "ok:hello"
            assert port.writeln("again")
            assert (await asyncio.wait_for(port.readline(), 0.5)).text == "ok:again"
            assert hooks == [1, 2]
            assert (port.connects, port.disconnects) == (2, 1)
            assert peer.commands == ["hello", "hello", "again"]
            await port.close()
            attempts = port.open_attempts
            await asyncio.sleep(0.1)
            assert port.open_attempts == attempts  # a closed port stops retrying

    run_on(loop_factory, body())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_binary_mode_hands_raw_bytes_and_connection_events_to_the_receiver(loop_factory):
    class Receiver:
        def __init__(self):
            self.data = bytearray()
            self.events = []

        def data_received(self, data):
            self.data += data

        def connection_made(self):
            self.events.append("made")

        def connection_lost(self, exc):
            self.events.append("lost")

    async def body():
        rx = Receiver()
        with PtyPeer("bin") as peer:
            async with SerialPort(peer.path, receiver=rx) as port:
                await asyncio.wait_for(port.wait_connected(), 1)
                peer.send(bytes(range(256)) + b"\n\r\x00")
                await until(lambda: len(rx.data) == 259)
                assert bytes(rx.data) == bytes(range(256)) + b"\n\r\x00"  # 8-bit clean, no line framing
                assert port.lines_received == 0
                peer.unplug()
                await until(lambda: rx.events == ["made", "lost"])
                peer.plug()
                await until(lambda: rx.events == ["made", "lost", "made"], timeout=1.0)

    run_on(loop_factory, body())


@pytest.mark.realtime
def test_skip_first_line_drops_the_fragment_a_streaming_device_leaves():
    async def body():
        with PtyPeer("stream") as peer:
            peer.send(b"stale\r\n")  # sent before the port opened: flushed by the open
            port = SerialPort(peer.path, skip_first_line=True)
            await port.start()
            await asyncio.wait_for(port.wait_connected(), 1)
            # the device was mid-reading when the port opened: the first "line" is a tail
            peer.send(b"34,1234\r\n1234,1250\r\n")
            line = await asyncio.wait_for(port.readline(), 0.5)
            assert line.text == "1234,1250"
            assert port.first_lines_skipped == 1
            await port.close()

    run_on(asyncio.SelectorEventLoop, body())


# ------------------------------------------------------------------------------------ virtual clock
def test_reconnect_backoff_follows_the_runtime_clock_exactly():
    """Retries after an unplug at T: T+0.05, +0.15, +0.35, +0.75, +1.55 (doubling from 50 ms)."""

    async def body():
        loop = asyncio.get_running_loop()
        clock = get_clock()
        assert clock.is_virtual
        with Echo("usb") as peer:
            port = SerialPort(peer.path, backoff_initial_s=0.05, backoff_max_s=1.0)
            await port.start()
            await until(lambda: port.connected)
            t0 = clock.now()
            await clock.sleep(1.0)
            peer.unplug()
            await until(lambda: port.disconnects == 1)
            unplugged_at = clock.now()
            assert unplugged_at == t0 + 1.0  # spinning on the loop did not move virtual time
            attempts_at = []
            real_open = port._open_serial

            def timed_open():  # runs in the executor; virtual time stands still meanwhile
                attempts_at.append(round(loop.time() - unplugged_at, 9))
                return real_open()

            port._open_serial = timed_open  # type: ignore[method-assign]
            loop.call_at(unplugged_at + 0.9, peer.plug)
            while not port.connected:
                await clock.sleep(0.01)
            assert attempts_at == [0.05, 0.15, 0.35, 0.75, 1.55]
            assert (port.open_failures, port.connects) == (4, 2)
            await port.close()

    run_on(lambda: VirtualClockLoop(), body())


@pytest.mark.realtime
def test_opening_runs_off_the_loop_thread():
    """The blocking open (termios set-up) happens in an executor, never on the event loop thread."""

    async def body():
        loop_thread = __import__("threading").get_ident()
        seen = []
        with PtyPeer("thr") as peer:
            port = SerialPort(peer.path)
            real = port._open_serial

            def spy():
                seen.append(__import__("threading").get_ident())
                return real()

            port._open_serial = spy  # type: ignore[method-assign]
            await port.start()
            await asyncio.wait_for(port.wait_connected(), 1)
            await port.close()
        assert seen and loop_thread not in seen

    run_on(asyncio.SelectorEventLoop, body())


@pytest.mark.realtime
def test_pty_peer_link_is_a_stable_by_id_style_symlink():
    async def body():
        peer = PtyPeer("gadget")
        peer.plug()
        first = os.readlink(peer.path)
        assert first.startswith("/dev/pts/") and peer.path.endswith("usb-asyncdonkey_gadget-if00")
        peer.unplug()
        assert not os.path.lexists(peer.path)
        peer.plug()
        assert os.readlink(peer.path) == peer.tty_path
        peer.close()
        assert not os.path.exists(os.path.dirname(peer.path))

    run_on(asyncio.SelectorEventLoop, body())
