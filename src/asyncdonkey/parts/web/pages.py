"""``Pages``: the browser pages connected to the web controller, and what is pushed to them.

One object knows which pages are open, what each was last told about control (``you``/``other``/``free``), how
the logs name each one (its address), and how a push reaches them from any thread: a tick run with
``executor=True`` calls :meth:`Pages.broadcast` off the loop, so every push goes through the loop the server
runs on, and a push before the server runs (or after it stopped) is a no-op.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

from aiohttp import web

from .desk import Desk

__all__ = ["Pages", "send_json"]


class Pages:
    """The open pages (WebSockets) of one controller.

    Args:
        desk: who drives; pages are counted there (a lone page may calibrate) and asked for their role.
    """

    def __init__(self, desk: Desk) -> None:
        self.desk = desk
        #: the loop the server runs on (set by the controller when it starts serving)
        self.loop: asyncio.AbstractEventLoop | None = None
        #: drive pages -> the role each was last told
        self.roles: dict[web.WebSocketResponse, str] = {}
        self._names: dict[object, str] = {}  # a page -> how the logs name it (its address)
        self._tasks: set[asyncio.Task[Any]] = set()

    def opened(self, ws: web.WebSocketResponse, request: web.Request) -> None:
        """A page connected: the desk counts it (a lone page may calibrate), the logs name it by its address."""
        self.desk.opened(ws)
        self._names[ws] = f"page {id(ws):x} from {request.remote or 'an unknown address'}"

    def closed(self, ws: web.WebSocketResponse) -> bool:
        """A page closed; true when it held control (now free)."""
        self.roles.pop(ws, None)
        self._names.pop(ws, None)
        return self.desk.closed(ws)

    def describe(self, client: object) -> str:
        """How the logs name a client: a page by its address, a ``POST`` script by its session."""
        return self._names.get(client) or _name(client)

    def tell_role(self, ws: web.WebSocketResponse, role: str) -> None:
        """Push ``role`` to a drive page unless it was the last role it was told."""
        if self.roles.get(ws) != role:
            self.roles[ws] = role
            self.send(ws, {"control": role})

    def push_roles(self, now: float) -> None:
        """Tell every drive page whose role changed (a handover, a release, a driver gone quiet)."""
        for ws in list(self.roles):
            self.tell_role(ws, self.desk.role(ws, now))

    def send(self, ws: web.WebSocketResponse, payload: dict[str, Any]) -> None:
        """Queue a push to one page; from the loop thread or any other (a tick run with ``executor=True``)."""
        loop = self.loop
        if loop is None or loop.is_closed():
            return
        try:
            here = asyncio.get_running_loop()
        except RuntimeError:
            here = None
        if here is not loop:
            loop.call_soon_threadsafe(self.send, ws, payload)
            return
        task = loop.create_task(send_json(ws, payload))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def broadcast(self, payload: dict[str, Any]) -> None:
        """Push to every drive page; safe from the tick (any thread), a no-op before the server runs."""
        loop = self.loop
        if loop is None or loop.is_closed() or not self.roles:
            return
        loop.call_soon_threadsafe(self.broadcast_now, payload)

    def broadcast_now(self, payload: dict[str, Any]) -> None:
        """Push to every drive page (on the server's loop)."""
        for ws in list(self.roles):
            self.send(ws, payload)

    async def close(self) -> None:
        """Close every drive page's socket (the car is shutting down) and drop the pushes still queued."""
        for ws in list(self.roles):
            with contextlib.suppress(Exception):
                await ws.close(code=1001, message=b"the car is shutting down")
        for t in list(self._tasks):
            t.cancel()


def _name(client: object) -> str:
    if client is None:
        return "a script without a session"
    return client if isinstance(client, str) else f"a page ({id(client):x})"


async def send_json(ws: web.WebSocketResponse, payload: dict[str, Any]) -> None:
    """Send one JSON message unless the socket is closed or closing (a page gone is not an error)."""
    if ws.closed:
        return
    with contextlib.suppress(ConnectionError, RuntimeError):
        await ws.send_json(payload)
