"""The drive URLs the web controller prints: every LAN address of the interfaces that are up, found by listing
the interfaces (not by resolving the hostname, which Debian and Pi OS map to 127.0.1.1), in the order a phone
should try them, ``<hostname>.local`` last; the QR code is the first.

Most tests describe a host by a fake interface table (``(name, flags, addresses)`` rows); one compares the
real enumeration with ``ip -o addr``, one opens the printed URL of a controller listening on every interface.
"""

from __future__ import annotations

import io
import re
import shutil
import socket
import subprocess

import aiohttp
import pytest
import segno

from asyncdonkey.parts.web import WebController
from asyncdonkey.parts.web.addresses import (
    IFF_LOOPBACK,
    IFF_RUNNING,
    IFF_UP,
    drive_urls,
    reachable_hosts,
    system_interfaces,
)

UP = IFF_UP | IFF_RUNNING | 0x1000  # up, carrier, multicast: what `ip link` shows as <UP,LOWER_UP,MULTICAST>
LO = IFF_UP | IFF_RUNNING | IFF_LOOPBACK
NO_CARRIER = IFF_UP | 0x1000  # up, but no cable / not associated
DOWN = 0x1000
TOKEN = "cFGA7O7vLabrlu-BTfdrfw"


def table(*rows):
    return lambda: list(rows)


LOOPBACK = ("lo", LO, ["127.0.0.1", "::1"])
WLAN = ("wlan0", UP, ["192.168.1.20", "fe80::ba27:ebff:fe12:3456%3"])


def urls(*rows, hostname="donkey"):
    return [u.url for u in drive_urls("http", 8887, f"/drive?token={TOKEN}", table(*rows), hostname)]


def test_a_loopback_only_host_offers_only_the_local_name_saying_no_lan_address_was_found():
    found = drive_urls("http", 8887, "/drive", table(LOOPBACK, ("eth0", DOWN, [])), "donkey")
    assert [u.url for u in found] == ["http://donkey.local:8887/drive"]
    assert "no LAN address found" in found[0].note


def test_a_pi_on_wifi_with_ethernet_down_lists_the_wifi_address_first_and_only_it():
    eth_down = ("eth0", DOWN, ["10.0.0.5"])  # a static address on an interface that is down
    eth_unplugged = ("eth1", NO_CARRIER, ["10.0.1.5"])
    assert urls(LOOPBACK, eth_down, eth_unplugged, WLAN) == [
        f"http://192.168.1.20:8887/drive?token={TOKEN}",
        f"http://donkey.local:8887/drive?token={TOKEN}",
    ]


def test_a_docker_bridge_comes_after_the_lan_and_is_marked():
    docker = ("docker0", UP, ["172.17.0.1"])  # a private address too, listed before wlan0
    found = drive_urls("http", 8887, "/drive", table(LOOPBACK, docker, WLAN), "donkey")
    assert [u.url for u in found] == [
        "http://192.168.1.20:8887/drive",
        "http://172.17.0.1:8887/drive",
        "http://donkey.local:8887/drive",
    ]
    assert found[0].reachable and not found[0].note
    assert not found[1].reachable and "this computer only" in found[1].note
    assert found[2].reachable and "mDNS" in found[2].note and "no LAN address" not in found[2].note


def test_with_only_a_bridge_the_local_name_leads_for_the_qr_code():
    found = drive_urls("http", 8887, "/drive", table(LOOPBACK, ("br-1a2b3c", UP, ["172.18.0.1"])), "donkey")
    assert [u.url for u in found] == ["http://donkey.local:8887/drive", "http://172.18.0.1:8887/drive"]
    assert "no LAN address found" in found[0].note


def test_private_ipv4_first_then_other_ipv4_then_global_ipv6_in_brackets_link_local_skipped():
    modem = ("wwan0", UP, ["100.72.3.4", "2a02:810d:4b3f:e100::7", "fe80::1%5"])
    eth = ("eth0", UP, ["169.254.10.20", "10.1.2.3", "fd12:3456::20", "fe80::2%2"])  # no DHCP: 169.254 too
    assert urls(modem, eth, WLAN) == [
        f"http://10.1.2.3:8887/drive?token={TOKEN}",
        f"http://192.168.1.20:8887/drive?token={TOKEN}",
        f"http://100.72.3.4:8887/drive?token={TOKEN}",
        f"http://[2a02:810d:4b3f:e100::7]:8887/drive?token={TOKEN}",
        f"http://[fd12:3456::20]:8887/drive?token={TOKEN}",
        f"http://donkey.local:8887/drive?token={TOKEN}",
    ]


def test_loopback_addresses_are_skipped_even_on_another_interface_and_duplicates_once():
    odd = ("dummy0", UP, ["127.0.1.1", "::1"])
    twice = ("wlan1", UP, ["192.168.1.20"])
    hosts = reachable_hosts(table(odd, WLAN, twice), "car.example.org")
    assert [(h.host, h.interface) for h in hosts] == [("192.168.1.20", "wlan0"), ("car.local", "")]


def controller(**kwargs) -> tuple[WebController, io.StringIO]:
    out = io.StringIO()
    ctr = WebController(port=8887, announce=out, qr=True, **kwargs)
    ctr.token = TOKEN  # what update() sets when the server starts
    return ctr, out


def test_the_controller_prints_every_url_with_its_port_and_token_and_the_qr_code_of_the_first():
    ctr, out = controller()
    ctr.interfaces = table(LOOPBACK, ("docker0", UP, ["172.17.0.1"]), WLAN, ("eth0", DOWN, []))
    found = ctr._urls()
    ctr._announce(found)
    text = out.getvalue()
    printed = re.findall(r"^  (\S+)(?:  \((.*)\))?$", text, re.MULTILINE)
    assert [u for u, _ in printed] == [
        f"http://192.168.1.20:8887/drive?token={TOKEN}",
        f"http://172.17.0.1:8887/drive?token={TOKEN}",
        f"http://{socket.gethostname().split('.')[0]}.local:8887/drive?token={TOKEN}",
        f"http://127.0.0.1:8887/drive?token={TOKEN}",  # a browser on the car, or on the laptop of a simulator
    ]
    assert "this computer only" in printed[1][1]
    assert printed[3][1] == "a browser on this computer"
    qr = io.StringIO()
    segno.make(printed[0][0], error="L").terminal(out=qr, compact=True)
    assert qr.getvalue() in text  # the QR code is the first URL's
    other = io.StringIO()
    segno.make(printed[2][0], error="L").terminal(out=other, compact=True)
    assert other.getvalue() not in text


def test_a_loopback_only_host_prints_the_local_name_with_the_note():
    ctr, out = controller()
    ctr.interfaces = table(LOOPBACK)
    ctr._announce(ctr._urls())
    lines = out.getvalue().splitlines()
    assert lines[1].startswith("  http://") and ".local:8887/drive?token=" in lines[1]
    assert "no LAN address found" in lines[1]
    assert lines[2] == f"  http://127.0.0.1:8887/drive?token={TOKEN}  (a browser on this computer)"
    assert not lines[3].startswith("  http")


@pytest.mark.parametrize(
    ("host", "expected"),
    [
        ("0.0.0.0", ["192.168.1.20", "127.0.0.1"]),
        ("::", ["[2a02:810d::7]", "[::1]"]),
        ("", ["192.168.1.20", "[2a02:810d::7]", "127.0.0.1"]),
    ],
)
def test_the_controller_prints_only_addresses_of_the_ip_versions_it_listens_on(host, expected):
    """The listener's IPv6 sockets are IPv6-only: ``0.0.0.0`` takes no IPv6 connection, ``::`` no IPv4 one."""
    ctr, _ = controller(host=host)
    ctr.interfaces = table(LOOPBACK, ("wlan0", UP, ["192.168.1.20", "2a02:810d::7", "fe80::1%3"]))
    hosts = [u.url.split("/")[2].rsplit(":", 1)[0] for u in ctr._urls()]
    local = f"{socket.gethostname().split('.')[0]}.local"
    assert hosts == [*expected[:-1], local, expected[-1]]  # loopback last: a browser on this computer


def test_a_controller_on_one_address_prints_that_address_only():
    ctr, _ = controller(host="192.168.1.20")
    ctr.interfaces = table(LOOPBACK, WLAN, ("eth0", UP, ["10.0.0.5"]))
    assert [u.url for u in ctr._urls()] == [f"http://192.168.1.20:8887/drive?token={TOKEN}"]


# -- the real machine -------------------------------------------------------------------------------------------
def ip_addr_shows() -> dict[str, set[str]]:
    """Every address ``ip -o addr`` lists, by interface, loopback excluded."""
    shown: dict[str, set[str]] = {}
    text = subprocess.run(["ip", "-o", "addr"], capture_output=True, text=True, check=True).stdout
    for line in text.splitlines():
        fields = line.split()
        name, family, cidr = fields[1], fields[2], fields[3]
        if name != "lo" and family in ("inet", "inet6"):
            shown.setdefault(name, set()).add(cidr.split("/")[0])
    return shown


@pytest.mark.subprocess
@pytest.mark.skipif(shutil.which("ip") is None, reason="no `ip` command (iproute2) to compare with")
def test_the_enumeration_finds_the_addresses_ip_addr_shows():
    shown = ip_addr_shows()
    listed = {
        name: {a.split("%")[0] for a in addresses}
        for name, flags, addresses in system_interfaces()
        if not flags & IFF_LOOPBACK and addresses
    }
    assert listed == shown


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_the_first_printed_url_opens_the_drive_page(tmp_path):
    """Listening on every interface, the car prints this machine's own addresses, and the first one serves
    the drive page (what a phone on the same network opens)."""
    from .web_rig import WebCar, driving

    if not any(h.reachable and not h.host.endswith(".local") for h in reachable_hosts()):
        pytest.skip("this machine has no LAN address up (only loopback)")
    out = io.StringIO()
    async with driving(WebCar(tmp_path, host="0.0.0.0", announce=out, qr=False)) as car:
        first = car.ctr.url
        assert first is not None and f":{car.ctr.port}/drive?token={car.ctr.token}" in first
        assert "127.0.0.1" not in first and ".local" not in first
        assert f"  {first}" in out.getvalue().splitlines()[1]
        jar = aiohttp.CookieJar(unsafe=True)
        async with aiohttp.ClientSession(cookie_jar=jar) as http, http.get(first) as r:
            assert r.status == 200 and "drive.js" in await r.text()
