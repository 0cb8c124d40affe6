"""JoystickReader against a FIFO fed with kernel-format events: bytes, init flag, partial reads, unplug."""

import asyncio
import struct

import pytest

from asyncdonkey.hw.joystick import (
    EVENT_SIZE,
    JS_EVENT_AXIS,
    JS_EVENT_BUTTON,
    JoystickReader,
    decode_events,
    encode_event,
)
from asyncdonkey.testing.joystick_model import JoystickModel


def test_event_layout_is_the_kernels():
    raw = encode_event(0x01020304, -2, JS_EVENT_AXIS, 5)
    assert raw == bytes([0x04, 0x03, 0x02, 0x01, 0xFE, 0xFF, 0x02, 0x05])
    assert EVENT_SIZE == 8
    init = encode_event(7, 1, JS_EVENT_BUTTON, 3, init=True)
    assert init[6] == 0x81
    (ev,), rest = decode_events(init)
    assert (ev.time_ms, ev.value, ev.kind, ev.number, ev.init) == (7, 1, JS_EVENT_BUTTON, 3, True)
    assert rest == b""


def test_decode_keeps_the_partial_tail():
    data = encode_event(1, 100, JS_EVENT_AXIS, 0) + encode_event(2, 1, JS_EVENT_BUTTON, 1)
    events, rest = decode_events(data[:11])
    assert [e.value for e in events] == [100]
    assert rest == data[8:11]
    events, rest = decode_events(rest + data[11:])
    assert [(e.kind, e.number, e.value) for e in events] == [(JS_EVENT_BUTTON, 1, 1)]
    assert rest == b""


async def settle(seconds=0.05):
    await asyncio.sleep(seconds)


@pytest.fixture
def pad(tmp_path):
    m = JoystickModel(tmp_path / "js0")
    yield m
    m.unplug()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_init_events_give_the_initial_state(tmp_path):
    model = JoystickModel(tmp_path / "js0", n_axes=3, n_buttons=2, plugged=False)
    model.axes[2] = -32767
    model.buttons[1] = True
    model.plug()
    seen = []
    reader = JoystickReader(model.path, on_event=seen.append)
    assert reader.open()
    await settle()
    assert [(e.kind, e.number, e.init) for e in seen] == [
        (JS_EVENT_BUTTON, 0, True),
        (JS_EVENT_BUTTON, 1, True),
        (JS_EVENT_AXIS, 0, True),
        (JS_EVENT_AXIS, 1, True),
        (JS_EVENT_AXIS, 2, True),
    ]
    assert reader.state.axis(2) == -1.0
    assert reader.state.button(1) is True
    assert reader.state.button(0) is False
    reader.close()
    model.unplug()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_axis_and_button_events_update_the_state(pad):
    reader = JoystickReader(pad.path)
    reader.open()
    await settle()
    pad.move_axis(0, 32767)
    pad.move_axis(4, -16384)
    pad.press(2)
    await settle()
    assert reader.state.axis(0) == 1.0
    assert reader.state.axis(4) == pytest.approx(-16384 / 32767)
    assert reader.state.button(2) is True
    pad.release(2)
    await settle()
    assert reader.state.button(2) is False
    assert reader.events == 6 + 11 + 4
    reader.close()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_an_event_split_across_two_writes_is_decoded_once(pad):
    seen = []
    reader = JoystickReader(pad.path, on_event=seen.append)
    reader.open()
    await settle()
    seen.clear()
    raw = pad.event_bytes(JS_EVENT_AXIS, 1, 12345)
    pad.write_raw(raw[:3])
    await settle()
    assert seen == []  # three bytes are not an event yet
    pad.write_raw(raw[3:] + pad.event_bytes(JS_EVENT_BUTTON, 0, 1)[:5])
    await settle()
    assert [(e.kind, e.number, e.value) for e in seen] == [(JS_EVENT_AXIS, 1, 12345)]
    pad.write_raw(pad.event_bytes(JS_EVENT_BUTTON, 0, 1)[5:])
    await settle()
    assert [(e.kind, e.number, e.value) for e in seen[1:]] == [(JS_EVENT_BUTTON, 0, 1)]
    assert reader.state.axis(1) == pytest.approx(12345 / 32767)
    reader.close()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_timestamps_and_values_come_through_byte_exact(pad):
    seen = []
    reader = JoystickReader(pad.path, on_event=seen.append)
    reader.open()
    await settle()
    seen.clear()
    pad.write_raw(struct.pack("<IhBB", 0xFFFFFFF0, -32767, 0x02, 7))
    await settle()
    (ev,) = seen
    assert (ev.time_ms, ev.value, ev.number, ev.is_axis, ev.init) == (0xFFFFFFF0, -32767, 7, True, False)
    reader.close()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_unplug_goes_neutral_and_a_replug_reconnects(pad):
    lost = []
    reader = JoystickReader(pad.path, reconnect_s=0.5, on_disconnect=lambda: lost.append(reader.state.axis(0)))
    task = asyncio.create_task(reader.run())
    await settle()
    pad.move_axis(0, 20000)
    pad.press(5)
    await settle()
    assert reader.connected and reader.state.axis(0) > 0.6
    pad.unplug()
    await settle()
    assert not reader.connected
    assert lost == [0.0]  # neutral before listeners hear of it
    assert reader.state.axis(0) == 0.0 and reader.state.button(5) is False
    assert reader.disconnects == 1
    await asyncio.sleep(2.0)  # retries every 0.5 s while the device is missing
    assert reader.open_failures >= 3
    pad.axes[0] = -32767  # the pad comes back with the stick held left: its init events say so
    pad.plug()
    await asyncio.sleep(0.6)
    assert reader.connected and reader.connects == 2
    assert reader.state.axis(0) == -1.0
    reader.close()
    await task
    assert not reader.connected


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_missing_device_is_retried_until_it_appears(tmp_path):
    reader = JoystickReader(tmp_path / "js1", reconnect_s=1.0)
    assert reader.open() is False
    assert "No such file" in reader.last_error
    await asyncio.sleep(2.5)
    assert reader.open_failures == 3
    model = JoystickModel(tmp_path / "js1")
    await asyncio.sleep(1.0)
    assert reader.connected
    reader.close()
    model.unplug()


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_reading_never_blocks_the_loop_on_a_real_loop(pad):
    reader = JoystickReader(pad.path)
    reader.open()
    loop = asyncio.get_running_loop()
    # With no bytes waiting, the loop keeps turning: 100 zero-sleeps take far less than a blocking read would.
    t0 = loop.time()
    for _ in range(100):
        await asyncio.sleep(0)
    assert loop.time() - t0 < 0.5
    pad.move_axis(3, 1000)
    for _ in range(200):
        if reader.state.axes.get(3) == 1000:
            break
        await asyncio.sleep(0.005)
    assert reader.state.axes[3] == 1000
    reader.close()
