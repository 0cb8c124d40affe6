"""The addresses a phone on the car's network can open: the drive URLs the web controller prints.

Why not ask the resolver. The obvious ``getaddrinfo(gethostname())`` finds nothing useful on a car: Debian and
Raspberry Pi OS map the hostname to ``127.0.1.1`` in ``/etc/hosts``, so the only URL printed was
``http://<hostname>.local:8887/…``, which a phone resolves only where mDNS is running on the car (avahi) and
understood by the phone. The addresses are read from the interfaces themselves instead.

Why ``getifaddrs(3)`` through ctypes. The other stdlib route is ``socket.if_nameindex()`` plus ``fcntl.ioctl``
(``SIOCGIFFLAGS``, ``SIOCGIFADDR``) for IPv4 and ``/proc/net/if_inet6`` for IPv6: two mechanisms, both
Linux-only, and ``SIOCGIFADDR`` returns one IPv4 address per interface, so a second address on ``wlan0`` (a
static one beside DHCP's) is missed. ``getifaddrs`` is one libc call that lists every address of every
interface, both families, with the interface's flags (glibc answers it over netlink, as ``ip addr`` does), and
it exists in the C library of Linux, macOS and the BSDs. It needs no dependency (``psutil`` or ``ifaddr`` would
do the same for one function). Where it is missing (Windows), the table is empty and only the ``.local`` name
is offered, with a note saying so.

What is offered, in order (:func:`reachable_hosts`):

1. IPv4 addresses of interfaces that are up and running (carrier present): private ranges first
   (``192.168/16``, ``10/8``, ``172.16/12``: the car's Wi-Fi or Ethernet), then any other;
2. global-scope IPv6 addresses (in brackets in the URL); link-local ones (``fe80::/10``, which need a zone
   the phone's browser cannot take) and IPv4 link-local ones (``169.254/16``, no DHCP) are left out;
3. addresses of container and virtual-machine bridges (``docker0``, ``br-…``, ``virbr0``, …), marked: only
   this computer reaches them;
4. ``<hostname>.local``, last, as an extra.

Loopback interfaces and addresses are never offered for a phone: it cannot reach them. A browser on the car
itself, or on the laptop that runs the simulator, can: :func:`loopback_url` is printed last, marked so.

The table is a parameter (:data:`InterfaceTable`: rows of ``(name, flags, addresses)``), so tests describe a
host's interfaces instead of depending on the machine's.
"""

from __future__ import annotations

import ctypes
import functools
import ipaddress
import socket
import sys
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass

__all__ = [
    "IFF_LOOPBACK",
    "IFF_RUNNING",
    "IFF_UP",
    "WILDCARD_VERSIONS",
    "DriveUrl",
    "HostAddress",
    "InterfaceRow",
    "InterfaceTable",
    "drive_urls",
    "loopback_url",
    "reachable_hosts",
    "system_interfaces",
]

#: interface flags (``<net/if.h>``; the same values on Linux, macOS and the BSDs)
IFF_UP = 0x1
IFF_LOOPBACK = 0x8
IFF_RUNNING = 0x40

#: one interface: its name, its flags and its addresses (text, IPv4 or IPv6; an IPv6 zone suffix is allowed)
InterfaceRow = tuple[str, int, Sequence[str]]
#: what lists the interfaces: :func:`system_interfaces`, or a fake in tests
InterfaceTable = Callable[[], Iterable[InterfaceRow]]

#: the IP versions a server listening on each wildcard address accepts (IPv6 sockets are IPv6-only, as asyncio
#: and the web controller's listener make them; ``""`` listens on both)
WILDCARD_VERSIONS: dict[str, tuple[int, ...]] = {"": (4, 6), "0.0.0.0": (4,), "::": (6,)}

#: interface name prefixes of container / VM bridges and their virtual ports: reachable from this host only
_BRIDGE_PREFIXES = (
    "docker",
    "br-",
    "veth",
    "virbr",
    "vnet",
    "lxcbr",
    "lxdbr",
    "incusbr",
    "podman",
    "cni",
    "flannel",
    "cali",
    "vboxnet",
    "vmnet",
)
_BRIDGE_NOTE = "a container/VM bridge: reachable from this computer only"
_NO_LAN_NOTE = (
    "no LAN address found (no network interface other than loopback is up with an address); "
    "this name works only if mDNS (avahi) answers for the car"
)
_MDNS_NOTE = "if the phone resolves mDNS .local names"
_LOOPBACK_NOTE = "a browser on this computer"


@dataclass(frozen=True)
class HostAddress:
    """An address to put in a URL: ``host`` is ready for it (IPv6 in brackets)."""

    host: str
    interface: str
    #: ``False`` for addresses a phone on the network cannot open (container bridges, the ``.local`` fallback is
    #: ``True``: it is the name to try when nothing else is found)
    reachable: bool = True
    note: str = ""


@dataclass(frozen=True)
class DriveUrl:
    """A URL to print, with a note on when it works (empty when it simply does)."""

    url: str
    reachable: bool = True
    note: str = ""


def reachable_hosts(
    table: InterfaceTable | None = None, hostname: str | None = None, versions: Collection[int] = (4, 6)
) -> list[HostAddress]:
    """This host's addresses in the order a phone should try them, ``<hostname>.local`` last (see the module).

    ``versions``: the IP versions the server listens on (``0.0.0.0`` is IPv4 only, ``::`` IPv6 only: printing
    an address it does not listen on would offer a URL that cannot connect).
    """
    rows = list((table or system_interfaces)())
    ranked: list[tuple[int, int, HostAddress]] = []
    for name, flags, addresses in rows:
        if not (flags & IFF_UP and flags & IFF_RUNNING) or flags & IFF_LOOPBACK:
            continue
        bridge = name.startswith(_BRIDGE_PREFIXES)
        for text in addresses:
            rank = _rank(text)
            if rank is None:
                continue
            ip = ipaddress.ip_address(text.split("%", 1)[0])
            if ip.version not in versions:
                continue
            host = f"[{ip}]" if ip.version == 6 else str(ip)
            if any(h.host == host for _, _, h in ranked):
                continue
            entry = HostAddress(host, name, reachable=not bridge, note=_BRIDGE_NOTE if bridge else "")
            ranked.append((10 + rank if bridge else rank, len(ranked), entry))
    hosts = [h for _, _, h in sorted(ranked, key=lambda r: r[:2])]
    name = hostname if hostname is not None else socket.gethostname()
    if name:
        found = any(h.reachable for h in hosts)
        hosts.append(HostAddress(f"{name.split('.')[0]}.local", "", note=_MDNS_NOTE if found else _NO_LAN_NOTE))
    return hosts


def drive_urls(
    scheme: str,
    port: int,
    path: str,
    table: InterfaceTable | None = None,
    hostname: str | None = None,
    versions: Collection[int] = (4, 6),
) -> list[DriveUrl]:
    """``scheme://<host>:<port><path>`` for every host of :func:`reachable_hosts`; the first is the one to
    show as a QR code."""
    hosts = reachable_hosts(table, hostname, versions)
    urls = [DriveUrl(f"{scheme}://{h.host}:{port}{path}", h.reachable, h.note) for h in hosts]
    # the first reachable one leads (container bridges rank below LAN addresses already; this covers a host
    # with only bridges, where the .local name is the better first guess)
    first = next((i for i, u in enumerate(urls) if u.reachable), 0)
    return [urls[first], *urls[:first], *urls[first + 1 :]] if urls else []


def loopback_url(scheme: str, port: int, path: str, versions: Collection[int] = (4, 6)) -> DriveUrl:
    """The URL a browser on this computer opens: ``127.0.0.1`` when the server takes IPv4 (a wildcard listener
    takes loopback too), ``[::1]`` when it listens on IPv6 alone. Never first: it is no use to a phone."""
    host = "127.0.0.1" if 4 in versions else "[::1]"
    return DriveUrl(f"{scheme}://{host}:{port}{path}", reachable=False, note=_LOOPBACK_NOTE)


def _rank(text: str) -> int | None:
    """0 private IPv4, 1 other IPv4, 2 global IPv6; ``None``: not for a phone (loopback, link-local, ...)."""
    try:
        ip = ipaddress.ip_address(text.split("%", 1)[0])
    except ValueError:
        return None
    if ip.is_loopback or ip.is_link_local or ip.is_multicast or ip.is_unspecified:
        return None
    if ip.version == 4:
        private = any(ip in net for net in _PRIVATE_V4)
        return 0 if private else 1
    if ip.ipv4_mapped is not None:
        return None
    return 2


_PRIVATE_V4 = tuple(ipaddress.ip_network(n) for n in ("192.168.0.0/16", "10.0.0.0/8", "172.16.0.0/12"))


# -- the system's table: getifaddrs(3) --------------------------------------------------------------------------
class _IfAddrs(ctypes.Structure):
    pass


_IfAddrs._fields_ = [
    ("ifa_next", ctypes.POINTER(_IfAddrs)),
    ("ifa_name", ctypes.c_char_p),
    ("ifa_flags", ctypes.c_uint),
    ("ifa_addr", ctypes.c_void_p),
    ("ifa_netmask", ctypes.c_void_p),
    ("ifa_ifu", ctypes.c_void_p),
    ("ifa_data", ctypes.c_void_p),
]

#: BSD and macOS sockaddrs start with a length byte, then a one-byte family; Linux's family is 16 bits
_BSD_SOCKADDR = sys.platform == "darwin" or "bsd" in sys.platform


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """The C library already loaded into the process (``dlopen(NULL)``); ``ctypes.util.find_library`` would
    run ``ldconfig`` in a subprocess at every start of the car."""
    try:
        lib = ctypes.CDLL(None, use_errno=True)
        lib.getifaddrs.argtypes = [ctypes.POINTER(ctypes.POINTER(_IfAddrs))]
        lib.getifaddrs.restype = ctypes.c_int
        lib.freeifaddrs.argtypes = [ctypes.POINTER(_IfAddrs)]
        lib.freeifaddrs.restype = None
    except (OSError, AttributeError, TypeError):
        return None
    return lib


def _sockaddr_text(ptr: int) -> str | None:
    """The address in a ``struct sockaddr`` (IPv4 or IPv6, with the IPv6 zone when it has one), else ``None``."""
    head = ctypes.string_at(ptr, 2)
    family = head[1] if _BSD_SOCKADDR else int.from_bytes(head, sys.byteorder)
    if family == socket.AF_INET:
        return socket.inet_ntop(socket.AF_INET, ctypes.string_at(ptr + 4, 4))
    if family == socket.AF_INET6:
        raw = ctypes.string_at(ptr, 28)  # family/len 2, port 2, flowinfo 4, address 16, scope id 4
        text = socket.inet_ntop(socket.AF_INET6, raw[8:24])
        scope = int.from_bytes(raw[24:28], sys.byteorder)
        return f"{text}%{scope}" if scope else text
    return None


def system_interfaces() -> list[InterfaceRow]:
    """This machine's interfaces with their flags and IPv4/IPv6 addresses (``getifaddrs``); ``[]`` where the C
    library has no ``getifaddrs`` or it fails."""
    lib = _libc()
    if lib is None:
        return []
    head = ctypes.POINTER(_IfAddrs)()
    if lib.getifaddrs(ctypes.byref(head)) != 0:
        return []
    table: dict[str, tuple[int, list[str]]] = {}
    try:
        node = head
        while node:
            entry = node.contents
            name = (entry.ifa_name or b"").decode(errors="replace")
            addresses = table.setdefault(name, (entry.ifa_flags, []))[1]
            if entry.ifa_addr:
                text = _sockaddr_text(entry.ifa_addr)
                if text is not None and text not in addresses:
                    addresses.append(text)
            node = entry.ifa_next
    finally:
        lib.freeifaddrs(head)
    return [(name, flags, addresses) for name, (flags, addresses) in table.items()]
