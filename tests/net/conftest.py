"""Fixtures of the Zenoh bridge tests (helpers in ``zenoh_loopback``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from asyncdonkey.parts.zenoh import ZenohLink

from .zenoh_loopback import connector, free_port, listener


@pytest.fixture
def link_pair() -> Iterator[Callable[[str], tuple[ZenohLink, ZenohLink]]]:
    """``make(prefix) -> (car_link, remote_link)``: a listening peer and a client connected to it."""
    links: list[ZenohLink] = []

    def make(prefix: str = "cars/test") -> tuple[ZenohLink, ZenohLink]:
        port = free_port()
        a = ZenohLink(prefix, listener(port))
        b = ZenohLink(prefix, connector(port))
        links.extend([a, b])
        return a, b

    yield make
    for link in links:
        link.close()
