"""What a car's ``build()`` opened, so that a car which refuses to start closes it and its process exits.

Why. ``asyncdonkey run`` calls the car file's ``build()``, and a build that raises part-way has usually opened
things already: a Zenoh session (whose callback threads are not daemon threads, so the interpreter waits on them
for ever at exit), sockets, a serial port, parts' threads. The exception leaves them to the garbage collector,
which stops no thread; the process said it failed and then kept running, still listening. So while ``build()``
runs inside :func:`collecting`, every :class:`~asyncdonkey.Vehicle` made is noted (:func:`note_vehicle`, called
by the Vehicle itself), and so is every close a part registers for what it opened (:func:`register_close`). If
``build()`` raises, :meth:`BuildScope.close` shuts each noted vehicle's parts down as the end of a drive does
(actuators first, each part bounded by its ``shutdown_timeout``, on daemon threads so that a hung one is
abandoned), then runs the registered closes, newest first.

Outside :func:`collecting` the notes are dropped at once: a vehicle built by a test or an application is never
kept alive by this module.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from .plan import Entry

__all__ = ["BuildScope", "collecting", "note_vehicle", "register_close"]

logger = logging.getLogger(__name__)

_lock = threading.Lock()
_active: list[BuildScope] = []


class BuildScope:
    """The vehicles made and the closes registered while one ``build()`` ran (see the module docstring)."""

    def __init__(self) -> None:
        self.vehicles: list[Any] = []
        self.closes: list[tuple[str, Callable[[], object]]] = []

    def close(self) -> list[str]:
        """Shut down the noted vehicles' parts, then run the registered closes (newest first), each once.

        Never raises: what fails is logged in one line naming it. Returns the names of what failed or did not
        finish in time (an empty list: everything was closed)."""
        with _lock:
            vehicles, closes = list(self.vehicles), list(self.closes)
            self.vehicles.clear()
            self.closes.clear()
        failed: list[str] = []
        for vehicle in vehicles:
            failed += shut_down_parts(getattr(vehicle, "parts", ()))
        for what, close in reversed(closes):
            try:
                close()
            except Exception as exc:
                logger.error("%s: closing it raised %s: %s", what, type(exc).__name__, exc)
                failed.append(what)
        return failed


@contextmanager
def collecting() -> Iterator[BuildScope]:
    """Note the vehicles made and the closes registered in this block (by any thread) in the scope it yields.

    Scopes nest: a note goes to the innermost one open."""
    scope = BuildScope()
    with _lock:
        _active.append(scope)
    try:
        yield scope
    finally:
        with _lock:
            _active.remove(scope)


def note_vehicle(vehicle: Any) -> None:
    """A :class:`~asyncdonkey.Vehicle` was made: note it in the open scope, if any."""
    with _lock:
        if _active:
            _active[-1].vehicles.append(vehicle)


def register_close(what: str, close: Callable[[], object]) -> None:
    """Something was opened (``what`` names it for an error message): ``close`` closes it, and must be safe to
    call after it was closed another way (a part's shutdown). Noted in the open scope, if any."""
    with _lock:
        if _active:
            _active[-1].closes.append((what, close))


def shut_down_parts(entries: Sequence[Any]) -> list[str]:
    """Shut the parts of a vehicle that never drove down: actuators first, then the rest, each phase's parts
    concurrently on daemon threads, each bounded by its ``shutdown_timeout``. Returns the names of the parts
    whose shutdown failed or was abandoned."""
    with_shutdown = [e for e in entries if isinstance(e, Entry) and e.shutdown.fn is not None]
    failed: list[str] = []
    for phase in ([e for e in with_shutdown if e.actuator], [e for e in with_shutdown if not e.actuator]):
        failed += _shut_down_phase(phase)
    return failed


def _shut_down_phase(entries: Sequence[Entry]) -> list[str]:
    outcomes: dict[str, BaseException | None] = {}
    threads: list[tuple[Entry, threading.Thread, float]] = []
    for e in entries:
        t = threading.Thread(target=_shut_down_one, args=(e, outcomes), name=f"shutdown:{e.name}", daemon=True)
        threads.append((e, t, time.monotonic() + e.shutdown.timeout + 0.5))
        t.start()
    failed: list[str] = []
    for e, t, deadline in threads:
        t.join(max(0.0, deadline - time.monotonic()))
        if t.is_alive():
            logger.error("part %r: shutdown() did not finish within %.1f s; abandoned", e.name, e.shutdown.timeout)
            failed.append(e.name)
        elif (exc := outcomes.get(e.name)) is not None:
            logger.error("part %r: shutdown() raised %s: %s", e.name, type(exc).__name__, exc)
            failed.append(e.name)
    return failed


def _shut_down_one(e: Entry, outcomes: dict[str, BaseException | None]) -> None:
    plan = e.shutdown
    fn = plan.fn
    kwargs = {"timeout": plan.timeout} if plan.takes_timeout else {}
    try:
        result = fn(**kwargs) if fn is not None else None
        if inspect.iscoroutine(result):  # an async shutdown, or a sync one handing back a coroutine
            asyncio.run(result)
    except BaseException as exc:
        outcomes[e.name] = exc
    else:
        outcomes[e.name] = None
