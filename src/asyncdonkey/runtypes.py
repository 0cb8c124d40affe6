"""The narrow views of a running drive that the modules around it need, as :class:`typing.Protocol` classes.

Why. The watchdog, the signal handler, shutdown and the pipelines each read a few fields of the drive in
progress. Typed against the whole ``Drive`` (or ``Vehicle``), each had to import the module that imports it,
and the core became one circle of modules. Each now names only what it reads, here, below all of them; the
``Drive`` and the ``Vehicle`` satisfy these protocols without knowing of them.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Sequence
from typing import Any, Protocol

__all__ = ["LoopActivity", "PipelineHost", "ShutdownScope", "Stoppable"]


class LoopActivity(Protocol):
    """What the loop thread is doing, read from other threads (the watchdog, the signal handler).

    ``current`` is the entry running now (``None`` between parts), ``part_started`` when it started on the
    runtime clock (``inf`` between parts)."""

    current: Any
    part_started: float
    entries: Sequence[Any]
    stop_grace_s: float


class Stoppable(Protocol):
    """A vehicle as the signal handler sees it: a stop request, and the drive in progress (or ``None``)."""

    def stop(self, reason: str = ...) -> None: ...

    @property
    def drive(self) -> LoopActivity | None: ...


class ShutdownScope(Protocol):
    """What shutdown takes down: the entries, the background work the drive owns, its watchdog."""

    entries: Sequence[Any]
    loop: asyncio.AbstractEventLoop
    tasks: list[tuple[Any, asyncio.Task[Any]]]
    threads: list[tuple[Any, threading.Thread]]
    executor: concurrent.futures.ThreadPoolExecutor | None
    watchdog: Any
    abandoned: list[str]


class PipelineHost(Protocol):
    """What the pipelines and reactions use of the drive they run beside (``runs``: each part's
    :class:`~asyncdonkey.partrun.PartRun` for this drive, in add() order)."""

    runs: Sequence[Any]
    loop: asyncio.AbstractEventLoop
    clock: Any
    mem: Any
    on: bool
    guards: Any
    push_sources: list[Any]

    def get_executor(self) -> concurrent.futures.ThreadPoolExecutor: ...

    def background_failed(self, e: Any, exc: BaseException, what: str = ...) -> None: ...
