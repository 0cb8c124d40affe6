"""The configs of ``asyncdonkey zenoh-pair`` on loopback: only the paired pilot moves the car's Memory.

The car runs the real subscriber part on the car config; the pilot, a fleet view and strangers use the
pilot/view configs or variations of them. Puts that the rules refuse must never reach the car's Memory.
"""

import asyncio
import json
import logging
import os
import stat
import time
from collections.abc import Callable

import pytest

from asyncdonkey.commands.cli import main
from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohLink, ZenohPublisher, ZenohSubscriber, zenoh_config
from asyncdonkey.parts.zenoh.link import exposure, link_config
from asyncdonkey.parts.zenoh.pairing import make_pair

from ..waiting import await_until
from .zenoh_loopback import free_port

CMD = ["pilot/angle", "pilot/throttle"]


async def _settled(read: Callable[[], int], quiet_s: float = 0.2, timeout_s: float = 5.0) -> int:
    """``read()`` once it has not changed for ``quiet_s`` (puts still in flight land first, however loaded the
    machine is)."""
    value, since = read(), time.monotonic()
    end = since + timeout_s
    while time.monotonic() < end:
        await asyncio.sleep(0.02)
        now_value = read()
        if now_value != value:
            value, since = now_value, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return value
    raise AssertionError(f"still changing after {timeout_s} s: {value}")


def _json5(path):
    return json.loads(path.read_text().split("\n", 1)[1])  # first line is a // comment


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("pair")
    port = free_port()
    files = make_pair(
        out, car="car1", pilot="laptop", car_hosts=["127.0.0.1"], port=port, listen_host="127.0.0.1", views=["base"]
    )
    other = make_pair(
        out / "other", car="car1", pilot="laptop", car_hosts=["127.0.0.1"], port=port, listen_host="127.0.0.1"
    )
    return files, other, port


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_only_the_paired_pilot_commands_the_car_and_views_still_read(pair):
    files, other, port = pair
    car = ZenohLink("cars/car1", files.car_config)
    pilot = ZenohLink("cars/car1", files.pilot_config)
    view = ZenohLink("cars/car1", files.view_configs["base"])
    # same CN "laptop", but a certificate of another pair's CA
    impostor = ZenohLink("cars/car1", other.pilot_config)
    # no TLS at all: a plain TCP session aimed at the car's port
    plain = ZenohLink(
        "cars/car1",
        zenoh_config(
            mode="peer",
            connect=[f"tcp/127.0.0.1:{port}"],
            multicast_scouting=False,
            extra={"connect/exit_on_failure": False},
        ),
    )
    links = [car, pilot, view, impostor, plain]
    try:
        sub = ZenohSubscriber(car, CMD)
        one_sample = ZenohSubscriber(car, CMD, group=PILOT_COMMAND, ping_every_s=0)
        telemetry = ZenohPublisher(car, ["sim/cte"])
        view_sub = ZenohSubscriber(view, ["sim/cte"], ping_every_s=0)
        pilot_pub = ZenohPublisher(pilot, CMD)
        view_pub = ZenohPublisher(view, CMD)
        impostor_pub = ZenohPublisher(impostor, CMD)
        plain_pub = ZenohPublisher(plain, CMD)
        update = asyncio.create_task(sub.update())
        # the allowed pilot drives (and its pongs reach the car: the round trip is allowed too)
        await await_until(lambda: (pilot_pub.run(0.1, 0.4, 0, 0), sub.received >= 2)[1])
        assert sub.run() == (0.1, 0.4)
        await await_until(lambda: car.pongs_received > 0)
        received = await _settled(lambda: sub.received)  # the pilot's last puts have landed
        # everyone else tries for half a second: full throttle, hard left
        for _ in range(25):
            for pub in (view_pub, impostor_pub, plain_pub):
                pub.run(-1.0, 1.0, 0, 0)
            await asyncio.sleep(0.02)
        assert sub.run() == (0.1, 0.4)  # the throttle stays where the allowed pilot put it
        assert sub.received == received and sub.unexpected == 0
        # ... and they cannot publish other keys of the car either (the rules drop them before the process)
        view.session.put("cars/car1/user/throttle", b"1.0")
        # the fleet view still reads the car's telemetry
        await await_until(lambda: (telemetry.run(0.05, 0.0), view_sub.received > 0)[1])
        assert view_sub.run() == 0.05
        # the allowed pilot still drives after all that
        await await_until(lambda: (pilot_pub.run(0.0, 0.2, 0, 0), sub.run() == (0.0, 0.2))[1])
        assert sub.unexpected == 0
        # the one-sample command (pilot/command) is the pilot's alone as well
        groups = {who: ZenohPublisher(who, CMD, group=PILOT_COMMAND) for who in (pilot, view, impostor, plain)}
        await await_until(lambda: (groups[pilot].run(0.3, 0.5, 0, 0), one_sample.run() == (0.3, 0.5))[1])
        taken = await _settled(lambda: one_sample.received)
        for _ in range(25):
            for who in (view, impostor, plain):
                groups[who].run(-1.0, 1.0, 0, 0)
            await asyncio.sleep(0.02)
        assert one_sample.run() == (0.3, 0.5) and one_sample.received == taken
        assert one_sample.counters()["refused"] == 0 and one_sample.unexpected == 0
        update.cancel()
    finally:
        for link in links:
            link.close()


@pytest.mark.network
def test_open_sessions_are_named_and_a_subscriber_on_one_warns(pair, caplog):
    files, _, port = pair
    assert exposure(zenoh_config(files.car_config)) == []
    assert exposure(zenoh_config(files.pilot_config)) == []
    loopback = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port + 1}"])
    assert exposure(loopback) == ["scouts by UDP multicast (it connects to the sessions it finds on the LAN)"]
    assert exposure(link_config(loopback)) == []  # loopback only, and the link turns Zenoh's scouting off
    assert exposure(zenoh_config(mode="peer", listen=["tcp/0.0.0.0:7447"], multicast_scouting=False)) == [
        "listens on tcp/0.0.0.0:7447 without TLS"
    ]
    assert exposure(link_config(zenoh_config(mode="client", connect=["tcp/192.0.2.1:7447"]))) == [
        "connects to tcp/192.0.2.1:7447 without TLS"
    ]
    assert exposure(link_config(zenoh_config(mode="peer", listen=["tls/0.0.0.0:7447"]))) == [
        "listens on tls/0.0.0.0:7447 without client certificates"
    ]
    assert "every interface" in exposure(None)[0]
    # a session listening on every interface is not opened here (tests bind loopback only): a loopback one
    # stands in, marked with what exposure() says of such a config
    link = ZenohLink(
        "cars/open", zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], multicast_scouting=False)
    )
    link.exposure = exposure(link_config(zenoh_config(mode="peer", listen=["tcp/0.0.0.0:7447"])))
    try:
        with caplog.at_level(logging.WARNING):
            ZenohSubscriber(link, ["cam/image_array"])  # not a command: taken, with a warning
        assert "anyone who can reach this session can write these channels" in caplog.text
        assert "listens on tcp/0.0.0.0:7447 without TLS" in caplog.text and "zenoh-pair" in caplog.text
    finally:
        link.close()


@pytest.mark.network  # (the pair fixture takes a free port)
def test_pair_writes_private_keys_owner_only_and_a_deny_by_default_car(pair):
    files, _, port = pair
    car = _json5(files.car_config)
    assert car["listen"]["endpoints"] == [f"tls/127.0.0.1:{port}"]  # no plain tcp listener
    tls = car["transport"]["link"]["tls"]
    assert tls["enable_mtls"] is True
    acl = car["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    commands = next(r for r in acl["rules"] if r["id"] == "pilot-commands")
    assert commands["flows"] == ["ingress"] and "cars/car1/pilot/throttle" in commands["key_exprs"]
    assert "cars/car1/pilot/command" in commands["key_exprs"]  # the one-sample command
    assert {"id": "pilot-host", "cert_common_names": ["laptop"]} in acl["subjects"]
    pilot = _json5(files.pilot_config)
    assert pilot["connect"]["endpoints"] == [f"tls/127.0.0.1:{port}"] and pilot["listen"]["endpoints"] == []
    assert pilot["scouting"]["multicast"]["enabled"] is False
    for key in [files.ca_key, files.car_dir / "car1-key.pem", files.pilot_dir / "laptop-key.pem"]:
        assert stat.S_IMODE(os.stat(key).st_mode) == 0o600
    assert not (files.car_dir / "ca-key.pem").exists() and not (files.pilot_dir / "ca-key.pem").exists()


def test_zenoh_pair_command(tmp_path, capsys):
    rc = main(
        [
            "zenoh-pair",
            str(tmp_path / "p"),
            "--car",
            "donkey7",
            "--pilot",
            "gpu-box",
            "--car-host",
            "10.0.0.7",
            "--car-host",
            "donkey7.local",
            "--view",
            "base",
            "--car-dir",
            "/home/pi/zenoh",
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "donkey7" in text and "gpu-box" in text and "ca-key.pem" in text
    car = _json5(tmp_path / "p" / "car" / "car.json5")
    assert car["transport"]["link"]["tls"]["root_ca_certificate"] == "/home/pi/zenoh/ca.pem"
    pilot = _json5(tmp_path / "p" / "pilot" / "pilot.json5")
    assert pilot["connect"]["endpoints"] == ["tls/10.0.0.7:7447"]
    assert (tmp_path / "p" / "base" / "base.json5").is_file()
    from cryptography import x509

    cert = x509.load_pem_x509_certificate((tmp_path / "p" / "car" / "donkey7-cert.pem").read_bytes())
    sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in sans.get_values_for_type(x509.IPAddress)] == ["10.0.0.7"]
    assert sans.get_values_for_type(x509.DNSName) == ["donkey7.local"]


def test_zenoh_pair_refuses_bad_names(tmp_path, capsys):
    assert main(["zenoh-pair", str(tmp_path), "--car", "a b"]) == 2
    assert "names are letters" in capsys.readouterr().err
    assert main(["zenoh-pair", str(tmp_path), "--car", "x", "--pilot", "x"]) == 2
