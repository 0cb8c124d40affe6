"""A refused TLS connection says why, on both sides, in Python's log: Zenoh refuses it in Rust and says nothing
there. Certificates made valid one hour ahead play a car (or a server) whose clock is an hour behind (a
Raspberry Pi without a clock battery before NTP answers)."""

from __future__ import annotations

import asyncio
import datetime
import logging
import types

import pytest

from asyncdonkey.parts.zenoh import PILOT_COMMAND, PilotServer, ZenohLink, ZenohPublisher, ZenohSubscriber
from asyncdonkey.parts.zenoh.certs import certificate_problems
from asyncdonkey.parts.zenoh.link import zenoh_config
from asyncdonkey.parts.zenoh.pairing import make_fleet, make_pair

from ..waiting import await_until
from .zenoh_loopback import free_port

CMD = ["pilot/angle", "pilot/throttle"]
AHEAD = datetime.timedelta(hours=1)


def _in_an_hour() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC) + AHEAD


class ConstantModel:
    pilot = types.SimpleNamespace(image_shape=(120, 160, 3))

    def infer(self, frames):
        return [(0.1, 0.5)] * len(frames)


def _not_valid_yet(caplog: pytest.LogCaptureFixture, who: str, cert: str) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.getMessage().startswith(f"{who}: ") and f"{cert} is not valid until" in r.getMessage()
    ]


def test_the_check_reads_the_windows_of_the_files_a_config_names(tmp_path):
    start = datetime.datetime(2030, 1, 1, 12, 0, tzinfo=datetime.UTC)
    files = make_pair(tmp_path, car="car1", pilot="laptop", car_hosts=["127.0.0.1"], not_before=start, days=10)
    cfg = zenoh_config(files.car_config)
    before = certificate_problems(cfg, now=start - AHEAD)
    assert before == [
        f"certificate {files.car_dir / 'car1-cert.pem'} is not valid until 2030-01-01 12:00:00 UTC; this machine's"
        " clock says 2030-01-01 11:00:00 UTC: check the clock (NTP)",
        f"CA certificate {files.car_dir / 'ca.pem'} is not valid until 2030-01-01 12:00:00 UTC (and so, probably,"
        " are the peers' certificates issued with it); this machine's clock says 2030-01-01 11:00:00 UTC: check the"
        " clock (NTP)",
    ]
    assert certificate_problems(cfg, now=start + datetime.timedelta(days=1)) == []
    after = certificate_problems(cfg, now=start + datetime.timedelta(days=11))
    assert len(after) == 2 and all("expired at 2030-01-11 12:05:00 UTC" in p and "zenoh-pair" in p for p in after)
    (files.car_dir / "ca.pem").write_text("not a certificate")
    assert "cannot be read as PEM certificates" in certificate_problems(cfg, now=start + datetime.timedelta(days=1))[0]
    assert certificate_problems(zenoh_config(mode="peer")) == []  # no TLS: nothing to check


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_car_whose_certificates_are_not_valid_yet_says_why_it_gets_no_command(tmp_path, caplog):
    port = free_port()
    files = make_pair(
        tmp_path, car="car1", pilot="laptop", car_hosts=["127.0.0.1"], port=port, listen_host="127.0.0.1",
        not_before=_in_an_hour(),
    )  # fmt: skip
    caplog.set_level(logging.INFO)
    car = ZenohLink("cars/car1", files.car_config)
    pilot = ZenohLink("cars/car1", files.pilot_config)
    try:
        # at start, each side names its own certificate and the clock
        assert len(_not_valid_yet(caplog, "ZenohLink 'cars/car1'", f"{files.car_dir / 'car1-cert.pem'}")) == 1
        assert len(_not_valid_yet(caplog, "ZenohLink 'cars/car1'", f"{files.pilot_dir / 'laptop-cert.pem'}")) == 1
        line = _not_valid_yet(caplog, "ZenohLink 'cars/car1'", "car1-cert.pem")[0]
        assert "this machine's clock says" in line and "check the clock (NTP)" in line and "no command" in line
        assert car.certificate_problems and pilot.certificate_problems
        commands = ZenohSubscriber(car, CMD, group=PILOT_COMMAND, ping_every_s=0.1, silent_after_s=0.4)
        sender = ZenohPublisher(pilot, CMD, group=PILOT_COMMAND)
        watching = asyncio.ensure_future(commands.update())
        for _ in range(40):  # the pilot sends for a second: the handshake fails, nothing arrives
            sender.run(0.0, 0.5, 0.0, 0.0)
            await asyncio.sleep(0.025)
        watching.cancel()
        assert commands.received == 0 and commands.silences == 1  # said once, not once per check
        silence = [r.getMessage() for r in caplog.records if "connected to no other Zenoh session" in r.getMessage()]
        assert len(silence) == 1
        assert "'cars/car1/pilot/command'" in silence[0] and "car1-cert.pem is not valid until" in silence[0]
    finally:
        pilot.close()
        car.close()


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_fleet_server_and_car_whose_certificates_are_not_valid_yet_say_why(tmp_path, caplog):
    port = free_port()
    files = make_fleet(
        tmp_path, cars=["car1"], server="gpu", server_hosts=["127.0.0.1"], port=port, listen_host="127.0.0.1",
        not_before=_in_an_hour(),
    )  # fmt: skip
    caplog.set_level(logging.INFO)
    server = PilotServer(
        ConstantModel(), ["car1"], config=zenoh_config(files.server_config), ping_every_s=0.1, silent_after_s=0.4
    )
    serving = asyncio.ensure_future(server.serve())
    car = ZenohLink("cars/car1", files.car_configs["car1"])
    try:
        assert len(_not_valid_yet(caplog, "pilot server", f"{files.server_dir / 'gpu-cert.pem'}")) == 1
        assert len(_not_valid_yet(caplog, "ZenohLink 'cars/car1'", f"{files.car_dirs['car1'] / 'car1-cert.pem'}")) == 1
        camera = ZenohPublisher(car, ["cam/image_array"])
        frame = bytes(120 * 160 * 3)
        for _ in range(40):
            camera.run(frame, 0.0)
            await asyncio.sleep(0.025)

        def server_said() -> list[str]:
            return [
                r.getMessage()
                for r in caplog.records
                if "'cars/car1/cam/image_array'" in r.getMessage() and "connected to no other" in r.getMessage()
            ]

        await await_until(lambda: len(server_said()) == 1, timeout=2.0)
        assert "gpu-cert.pem is not valid until" in server_said()[0]  # its certificates checked again
        assert server.counters()["car1"]["answered"] == 0
    finally:
        server.stop()
        await serving
        car.close()
        server.close()


@pytest.mark.network
def test_valid_certificates_say_nothing(tmp_path, caplog):
    files = make_pair(
        tmp_path, car="car1", pilot="laptop", car_hosts=["127.0.0.1"], port=free_port(), listen_host="127.0.0.1"
    )
    caplog.set_level(logging.WARNING)
    car = ZenohLink("cars/car1", files.car_config)
    try:
        assert car.certificate_problems == [] and "not valid" not in caplog.text and "expired" not in caplog.text
    finally:
        car.close()


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_connected_subscriber_that_hears_nothing_says_so_once_and_again_when_samples_come(link_pair, caplog):
    car, pilot = link_pair("cars/c1")
    caplog.set_level(logging.INFO, logger="asyncdonkey.parts.zenoh.parts")
    commands = ZenohSubscriber(car, CMD, group=PILOT_COMMAND, ping_every_s=0, silent_after_s=0.3)
    watching = asyncio.ensure_future(commands.update())
    try:
        await await_until(lambda: commands.silences == 1, timeout=3.0)
        await asyncio.sleep(0.4)  # still silent: said once
        lines = [r.getMessage() for r in caplog.records]
        assert len(lines) == 1 and commands.silences == 1
        assert "nothing on 'cars/c1/pilot/command'" in lines[0]
        assert "connected to 1 other Zenoh session(s)" in lines[0] and "access rules" in lines[0]
        sender = ZenohPublisher(pilot, CMD, group=PILOT_COMMAND)
        await await_until(lambda: (sender.run(0.0, 0.2, 0.0, 0.0), "samples arrive again" in caplog.text)[1])
        assert commands.run() == (0.0, 0.2)
    finally:
        watching.cancel()
