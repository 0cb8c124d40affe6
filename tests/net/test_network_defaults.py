"""A link is closed unless told otherwise, and a command subscriber refuses a session others can publish to.

These tests open sessions on 127.0.0.1 only. Where a session listening on every interface is needed, a loopback
session stands in, marked with what :func:`exposure` says of the open config (what the link computes from it).
"""

import json
import logging
import os
import re
from pathlib import Path

import pytest

from asyncdonkey.parts.zenoh import (
    COMMAND_CHANNELS,
    PILOT_COMMAND,
    ZenohConfigError,
    ZenohLink,
    ZenohSubscriber,
    link_config,
    zenoh_config,
)
from asyncdonkey.parts.zenoh.link import LOOPBACK_LISTEN, exposure
from asyncdonkey.parts.zenoh.pairing import make_pair

from .zenoh_loopback import free_port, listener

pytestmark = [pytest.mark.network]

CMD = ["pilot/angle", "pilot/throttle"]
OPEN = "tcp/0.0.0.0:7447"


def _sockets() -> set[tuple[str, str, str]]:
    """This process's sockets as ``(protocol, local address, state)`` from /proc (state ``0A``: listening)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        m = re.fullmatch(r"socket:\[(\d+)\]", target)
        if m:
            inodes.add(m.group(1))
    out = set()
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        for line in Path(f"/proc/net/{proto}").read_text().splitlines()[1:]:
            f = line.split()
            if f[9] in inodes:
                out.add((proto, f[1], f[3]))
    return out


def _host(address: str) -> str:
    """``0100007F:1F90`` → ``127.0.0.1`` (IPv4 only: a loopback listener here is IPv4)."""
    hexip = address.split(":")[0]
    return ".".join(str(int(hexip[i : i + 2], 16)) for i in (6, 4, 2, 0)) if len(hexip) == 8 else hexip


def _open_link(**kw) -> ZenohLink:
    """A loopback link marked as Zenoh's open defaults would make it (listening on every interface)."""
    link = ZenohLink("cars/open", listener(free_port()), **kw)
    link.exposure = exposure(link_config(zenoh_config(mode="peer", listen=[OPEN])))
    return link


def test_a_link_without_a_config_listens_on_loopback_only_and_does_not_scout():
    cfg = link_config(None)
    assert json.loads(cfg.get_json("listen/endpoints")) == LOOPBACK_LISTEN
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    before = _sockets()
    link = ZenohLink("cars/defaults")
    try:
        new = _sockets() - before
        listening = [(proto, addr) for proto, addr, state in new if proto.startswith("tcp") and state == "0A"]
        assert listening and all(proto == "tcp" and _host(addr) == "127.0.0.1" for proto, addr in listening), new
        assert not [s for s in new if s[0].startswith("udp")], new  # no multicast scouting socket
        assert link.exposure == []
        ZenohSubscriber(link, CMD).shutdown()  # commands on a closed session: taken without a word
    finally:
        link.close()


def test_what_a_config_leaves_unset_is_closed_and_what_it_says_is_kept():
    connect_only = zenoh_config(mode="peer", connect=["tcp/127.0.0.1:7447"])
    cfg = link_config(connect_only)
    assert json.loads(cfg.get_json("listen/endpoints")) == LOOPBACK_LISTEN
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert cfg is connect_only  # filled in place: a copy would lose the secrets a config holds inline
    explicit = link_config(zenoh_config(mode="peer", listen=[OPEN], multicast_scouting=True))
    assert json.loads(explicit.get_json("listen/endpoints")) == [OPEN]
    assert exposure(explicit) == [
        f"listens on {OPEN} without TLS",
        "scouts by UDP multicast (it connects to the sessions it finds on the LAN)",
    ]


@pytest.mark.parametrize("channels", [CMD, ["user/mode"], ["recording"], ["throttle"], ["user/angle", "sim/cte"]])
def test_command_channels_on_a_session_others_can_publish_to_are_refused_naming_the_endpoint(channels):
    link = _open_link()
    try:
        with pytest.raises(ZenohConfigError) as refused:
            ZenohSubscriber(link, channels)
        text = str(refused.value)
        assert f"listens on {OPEN} without TLS" in text and "access-control rules" in text
        assert "insecure=True" in text and "zenoh-pair" in text
        with pytest.raises(ZenohConfigError, match=re.escape(OPEN)):
            ZenohSubscriber(link, CMD, group=PILOT_COMMAND)
        assert link._users == 0  # a refused subscriber holds nothing
    finally:
        link.close()


def test_insecure_true_takes_commands_on_an_open_session_with_a_warning(caplog):
    link = _open_link(insecure=True)
    try:
        with caplog.at_level(logging.WARNING):
            sub = ZenohSubscriber(link, CMD)
        assert "anyone who can reach this session can write these channels" in caplog.text
        assert OPEN in caplog.text and "insecure=True" in caplog.text
        sub.shutdown()
    finally:
        link.close()


def test_the_command_channels_are_donkeycars():
    assert {"user/angle", "user/throttle", "pilot/angle", "pilot/throttle", "angle", "throttle"} <= COMMAND_CHANNELS
    assert {"user/mode", "recording", PILOT_COMMAND} <= COMMAND_CHANNELS
    assert "cam/image_array" not in COMMAND_CHANNELS


def _json5(path: Path) -> dict:
    return json.loads(path.read_text().split("\n", 1)[1])  # first line is a // comment


def test_mutual_tls_without_access_rules_is_refused_for_commands(tmp_path):
    """Mutual TLS alone lets every holder of a certificate from the CA connect, a fleet view's too: without
    access rules each of them could command the car."""
    port = free_port()
    files = make_pair(tmp_path, car="car1", car_hosts=["127.0.0.1"], port=port, listen_host="127.0.0.1")
    doc = _json5(files.car_config)
    del doc["access_control"]
    no_rules = tmp_path / "car-no-rules.json5"
    no_rules.write_text(json.dumps(doc))
    link = ZenohLink("cars/car1", no_rules)  # a real mutual-TLS listener on 127.0.0.1
    try:
        assert link.exposure == [
            f"listens on tls/127.0.0.1:{port} with mutual TLS but no access-control rules: any holder of a"
            " certificate from its CA could command the car"
        ]
        with pytest.raises(ZenohConfigError, match="any holder of a certificate from its CA could command the car"):
            ZenohSubscriber(link, CMD, group=PILOT_COMMAND)
        ZenohSubscriber(link, ["sim/cte"]).shutdown()  # not a command: taken (with a warning)
    finally:
        link.close()
    paired = ZenohLink("cars/car1", files.car_config)  # the same with zenoh-pair's rules: closed
    try:
        assert paired.exposure == []
        ZenohSubscriber(paired, CMD, group=PILOT_COMMAND).shutdown()
    finally:
        paired.close()
