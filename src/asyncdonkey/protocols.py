"""The part contract as :class:`typing.Protocol` classes: what the drive loop looks for on a part.

A part needs only the methods of its kind; ``Vehicle.add`` checks them once and decides how to call the part.
These protocols are for type checkers and for reading: no part has to inherit from anything.

* :class:`Part`: ``run(*inputs)``, sync (called inline, or in a worker with ``executor=True``) or ``async``
  (awaited in order).
* :class:`ThreadedPart`: Donkeycar's threaded part: ``update()`` loops in its own thread, ``run_threaded()`` is
  called each tick. An ``async def update()`` runs as a task beside the ticks instead.
* :class:`OriginSource`: a part that knows how old the sensing behind its outputs is (a camera, a sensor
  poller, a controller, a network receiver) says so with ``output_origin()``; every other part's outputs
  inherit the origin of its inputs (``docs/provenance.md``).
* :class:`Actuator`: a part that drives hardware and has a safe state (throttle stopped, steering centred).
  The drive loop puts every actuator in its safe state first at shutdown, and the watchdog (a thread outside
  the event loop) does it when the actuator's command goes stale, whatever the loop thread is doing.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

__all__ = ["Actuator", "OriginSource", "Part", "ThreadedPart"]


@runtime_checkable
class Part(Protocol):
    def run(self, *inputs: Any) -> Any: ...


@runtime_checkable
class ThreadedPart(Protocol):
    def update(self) -> Any: ...
    def run_threaded(self, *inputs: Any) -> Any: ...


@runtime_checkable
class OriginSource(Protocol):
    def output_origin(self) -> float | None:
        """Runtime-clock time of the sensing behind the values the last ``run()`` returned.

        Called right after each ``run()``/``run_threaded()`` that returned a value. ``None`` means "inherit
        from my inputs" (or, for a part without inputs, "now").
        """
        ...


@runtime_checkable
class Actuator(Protocol):
    def safe_state_sync(self) -> None:
        """Put the output in its safe state now. Called from any thread; must be quick and bounded."""
        ...

    def command_deadline(self) -> float:
        """Runtime-clock time at which the current command goes stale (``inf``: it never does)."""
        ...

    def attach(self, runtime: Any) -> None:
        """At a drive's start, receive its :class:`~asyncdonkey.watchdog.ActuatorRuntime` (the latency recorder
        ``record_latency(t, origin)`` and ``deadline_changed(deadline)`` for the watchdog); ``None`` at its end."""
        ...
