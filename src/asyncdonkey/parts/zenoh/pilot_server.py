"""A fleet on one pilot server: every car's frames in, one batched model call, each car its own command back.

::

    server = PilotServer(BatchPilot("pilot.onnx"), ["car1", "car2", "car3"], config="pair/server/server.json5")
    await server.serve()                      # until server.stop(); `asyncdonkey pilot-server` wraps this

**Channel contracts as the remote pilot's.** For each car the server takes ``cam/image_array`` from
``cars/<car>`` with a :class:`.ZenohSubscriber` (the frame checked against the channel's contract, its origin
carried across the network, the round trip measured) and answers with a :class:`.ZenohPublisher` of
``pilot/angle, pilot/throttle`` as one sample on ``cars/<car>/pilot/command`` (``group=PILOT_COMMAND``), aged
by *that car's frame*: the car's ``pilot/throttle@age`` is its own camera-to-command time, exactly as with
``examples/remote_pilot.py``. A car needs no change to move from its own remote pilot to a server.

**Batching** (:class:`.FrameBatcher`): the first frame to arrive opens a window of ``window_s`` (5 ms by
default); the newest frame of each car that arrived by then goes into one model call
(:class:`.BatchPilot`), in arrival order; a frame older than ``max_age_s`` (the cars' failsafe window) is not
inferred (``too_old``). The call runs in the server's own worker thread, so Zenoh's callbacks and the event
loop keep taking frames meanwhile; those form the next batch as soon as the call returns.

**What the server never does**: keep a car moving. It has no failsafe of its own and needs none: a car whose
server is slow, overloaded or gone stops by its own stale-command stop (``PWMThrottle``'s failsafe or
:class:`~asyncdonkey.parts.failsafe.StaleCommandStop`), unchanged, because the commands it gets stop being
fresh. Who may command which car is the job of the fleet configs of ``asyncdonkey zenoh-pair --fleet``
(:mod:`.pairing`).

Counters: :meth:`counters` per car (``frames``, ``replaced``, ``too_old``, ``batched``, ``answered``,
``refused``) and :attr:`batch_sizes`, :attr:`infer_s` (recent model-call times), :attr:`calls`.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import inspect
import logging
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

from ...clock import get_clock
from .batcher import Frame, FrameBatcher
from .link import ZenohLink, link_config
from .pairing import PILOT_COMMAND
from .parts import ZenohPublisher, ZenohSubscriber

__all__ = ["PilotServer"]

logger = logging.getLogger(__name__)

CAMERA = "cam/image_array"
COMMAND = ("pilot/angle", "pilot/throttle")
#: what a model gives for a batch: one ``(angle, throttle)`` per frame, or ``None`` (no command for that car)
Commands = Sequence[tuple[float, float] | None]


class _Car:
    """One car's channels on the server: its frames in, its commands out, on the shared session."""

    def __init__(self, name: str, session: Any, prefix: str, ping_every_s: float) -> None:
        self.name = name
        self.link = ZenohLink(prefix, session=session)
        self.frames = ZenohSubscriber(self.link, [CAMERA], ping_every_s=ping_every_s)
        self.commands = ZenohPublisher(self.link, list(COMMAND), group=PILOT_COMMAND)
        self.answered = 0

    def close(self) -> None:
        for part in (self.frames, self.commands):
            try:
                part.shutdown()
            except Exception:  # pragma: no cover - closing a session that is going away
                pass


class PilotServer:
    """Serve a fleet's pilot commands from one model (see the module docstring).

    Args:
        model: a :class:`.BatchPilot`, or any ``infer(frames) -> [(angle, throttle) | None, ...]`` callable
            (sync: run in the server's worker thread; async: awaited on the loop).
        cars: the car names; each car's keys are ``prefix.format(car=name)``.
        config: the Zenoh config (a ``zenoh.Config``, a file such as ``server.json5`` from ``zenoh-pair
            --fleet``, or ``None``: loopback only); or give ``session``.
        session: an open Zenoh session to use (not closed by the server).
        window_s: how long the first frame of a batch waits for the other cars' frames.
        max_age_s: the cars' failsafe window: a frame older than this when its batch is taken is not inferred.
        max_batch: the most frames per model call.
        prefix: the key prefix of a car, with ``{car}`` for its name.
        ping_every_s: round-trip measurement per car (keeps the frames' ages true; 0: never).
    """

    def __init__(
        self,
        model: Any,
        cars: Sequence[str],
        *,
        config: Any = None,
        session: Any = None,
        window_s: float = 0.005,
        max_age_s: float = 0.25,
        max_batch: int = 32,
        prefix: str = "cars/{car}",
        ping_every_s: float = 0.5,
    ) -> None:
        names = list(dict.fromkeys(cars))
        if not names or isinstance(cars, str):
            raise ValueError(f"PilotServer: give the car names as a list, got {cars!r}")
        if "{car}" not in prefix:
            raise ValueError(f"PilotServer: prefix must contain '{{car}}', got {prefix!r}")
        self.infer: Callable[[Sequence[Any]], Commands | Awaitable[Commands]] = getattr(model, "infer", model)
        self.model = model
        self.batcher = FrameBatcher(window_s=window_s, max_age_s=max_age_s, max_batch=max_batch)
        self._owned = session is None
        if session is None:
            import zenoh

            session = zenoh.open(link_config(config))
        self.session = session
        self.cars: dict[str, _Car] = {}
        try:
            for name in names:
                self.cars[name] = _Car(name, session, prefix.format(car=name), ping_every_s)
        except Exception:
            self.close()
            raise
        self.batch_sizes: collections.deque[int] = collections.deque(maxlen=10_000)
        self.infer_s: collections.deque[float] = collections.deque(maxlen=10_000)
        self.calls = 0
        self.errors = 0
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._stop: asyncio.Event | None = None
        self._unsubscribe: list[Callable[[], None]] = []

    # -- frames in (Zenoh's threads, handed to the loop) --------------------------------------------------
    def offer(self, car: str, image: Any, origin: float) -> None:
        """Take a frame on the loop thread (the subscribers' pushes call this through the loop)."""
        now = get_clock().now()
        self.batcher.offer(Frame(car, image, origin, now))
        if self._wake is not None:
            self._wake.set()

    def _push(self, car: str) -> Callable[[Any, float], None]:
        loop = self._loop
        assert loop is not None

        def push(image: Any, origin: float) -> None:
            try:
                loop.call_soon_threadsafe(self.offer, car, image, origin)
            except RuntimeError:  # the loop is closed: the server is going away
                pass

        return push

    # -- the serving loop ----------------------------------------------------------------------------------
    async def serve(self) -> None:
        """Take frames, infer them in batches and answer each car, until :meth:`stop`."""
        self._loop = asyncio.get_running_loop()
        clock = get_clock()
        self._wake, self._stop = asyncio.Event(), asyncio.Event()
        for car in self.cars.values():
            car.link.now = clock.now
            self._unsubscribe.append(car.frames.subscribe(self._push(car.name)))
        pings = [asyncio.ensure_future(car.frames.update()) for car in self.cars.values()]
        stopping = asyncio.ensure_future(self._stop.wait())
        try:
            while not self._stop.is_set():
                due = self.batcher.due()
                if due is None:
                    self._wake.clear()
                    waking = asyncio.ensure_future(self._wake.wait())
                    await asyncio.wait([waking, stopping], return_when=asyncio.FIRST_COMPLETED)
                    waking.cancel()
                    continue
                if clock.now() < due:
                    await clock.sleep_until(due)
                await self._serve_batch(self.batcher.take(clock.now()))
        finally:
            stopping.cancel()
            for task in pings:
                task.cancel()
            for unsubscribe in self._unsubscribe:
                unsubscribe()
            self._unsubscribe.clear()

    async def _serve_batch(self, batch: list[Frame]) -> None:
        if not batch:
            return
        clock = get_clock()
        images = [f.image for f in batch]
        t0 = clock.now()
        try:
            if inspect.iscoroutinefunction(self.infer):
                result = await self.infer(images)
            else:  # a model call holds its thread for milliseconds: never the loop's
                if self._executor is None:
                    self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pilot-server")
                result = await asyncio.get_running_loop().run_in_executor(self._executor, self.infer, images)
        except Exception as exc:
            self.errors += 1
            logger.warning("pilot server: the model failed on a batch of %d (%s): no commands", len(batch), exc)
            return
        self.infer_s.append(clock.now() - t0)
        self.batch_sizes.append(len(batch))
        self.calls += 1
        now = clock.now()
        for frame, command in zip(batch, result, strict=True):
            if command is None:
                continue
            car = self.cars[frame.car]
            age = max(0.0, now - frame.origin)
            car.commands.run(command[0], command[1], age, age)
            car.answered += 1

    def stop(self) -> None:
        """End :meth:`serve` (from the loop's thread)."""
        if self._stop is not None:
            self._stop.set()

    def counters(self) -> dict[str, dict[str, int]]:
        """Per car: the batcher's counters plus ``answered`` (commands sent) and ``refused`` (frames the channel
        contract refused)."""
        out = self.batcher.counters()
        for name, car in self.cars.items():
            row = out.setdefault(name, {"frames": 0, "replaced": 0, "too_old": 0, "batched": 0})
            row["answered"] = car.answered
            row["refused"] = car.frames.counters()["refused"]
        return out

    def close(self) -> None:
        """Undeclare every car's channels, stop the worker thread and close the session (if the server opened
        it)."""
        for car in self.cars.values():
            car.close()
        ex, self._executor = self._executor, None
        if ex is not None:
            ex.shutdown(wait=True)
        if self._owned:
            try:
                self.session.close()
            except Exception:  # pragma: no cover
                pass
