"""How one part is called each tick, decided once when it is added (``Vehicle.add``).

Everything a tick needs about a part is worked out here, so the tick itself only walks a list of prepared
:class:`Entry` objects (as each drive's :class:`~asyncdonkey.core.partrun.PartRun` holds them): no per-tick
``hasattr``/``isinstance``. That includes where the values it returns get their *origin* (the time of the
sensing behind them), by the invariant of ``docs/provenance.md``: no value is ever dated younger than the
sensing that could have produced it.

* a part that states its own origin (``output_origin()``: a camera, a sensor poller, a controller, a network
  receiver) gives its outputs that origin;
* a part without inputs is a source: its outputs are sensed when it returns;
* a declared selector (``output_sources()``, or a Donkeycar template class recognised by its interface:
  :mod:`.selectors`) gives each output the oldest origin of the inputs it declares for that call;
* any other part's outputs get the **oldest** origin among all its inputs that have one (a channel never written
  has none; an ``@age`` input counts as its channel). Nothing about who wrote an input or when changes that, so
  the order and names of the writes cannot make a value younger: a switched-off pilot's last throttle passed on
  by a filter writing back to its own channel is as old as that throttle. No input with an origin: the output
  has none, its age is infinite. When such an output is a mutable input object (an array the part may have
  written the other inputs into), every channel holding that object is aged to the same origin.

A part that did not run (run condition false, returned ``None``, raised under ``on_error="continue"``) stores
nothing: its channels keep their origins. The cost per call is one ``min`` over the inputs' origins and one type
lookup per output; a part reading a single channel copies that channel's origin.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import enum
import inspect
import itertools
import logging
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, TypeGuard

from ..contracts import ContractViolation
from ..errors import OutputCountError, PartSpecError, PartTimeoutError
from ..memory import Memory
from .origin_sources import OutputSources, declared_sources

if TYPE_CHECKING:
    from ..contracts import Contract, Contracts

__all__ = [
    "AGE_SUFFIX",
    "Background",
    "BesideTicks",
    "Entry",
    "OnError",
    "PartOptions",
    "ShutdownPlan",
    "build_entry",
    "checked_store",
]

logger = logging.getLogger("asyncdonkey.loop")

OnError = Literal["stop", "continue"]
AGE_SUFFIX = "@age"
_INF = math.inf
#: the origin of a value with nothing sensed behind it (computed only from channels that have no origin): such an
#: output is stored without an origin, so its age is infinite, as a never-written channel's
_NEVER = -math.inf
#: as many ``inf`` as any part has inputs: the default of ``map(origins.get, channels, _INFS)``
_INFS = itertools.repeat(_INF)
#: types whose instances cannot change: what ``_immutable`` has found so (numbers, strings, enums, numpy scalars),
#: looked up directly on the hot path
_IMMUTABLE_TYPES: set[type] = {int, float, bool, complex, str, bytes, type(None), range, type(Ellipsis)}
#: immutable containers: as immutable as their items
_CONTAINERS = (tuple, frozenset)
#: every other type met: whether its instances cannot change (``_immutability_of``)
_TYPE_KIND: dict[type, bool] = {}

#: Classes whose ``shutdown()`` puts an actuator in its safe state, recognised so that Donkeycar's own
#: actuator parts, used unchanged, are shut down in the first (safe-state) phase like ours.
_DONKEYCAR_ACTUATOR_MODULES = ("donkeycar.parts.actuator",)


class Background(enum.Enum):
    """What runs beside the ticks for a part, decided at ``add()``."""

    NONE = "none"  #: nothing: the part only runs in the tick
    THREAD = "thread"  #: Donkeycar's threaded part: its sync ``update()`` loops in a thread of its own
    TASK = "task"  #: an ``async def update()``: a task on the drive's event loop


def background_of(threaded: bool, async_update: bool) -> Background:
    """An ``async def update()`` is always a task; a sync one runs in a thread only for ``threaded=True``."""
    if async_update:
        return Background.TASK
    return Background.THREAD if threaded else Background.NONE


@dataclass(frozen=True, slots=True, kw_only=True)
class PartOptions:
    """What ``Vehicle.add()`` is given for one part, besides the part itself: :func:`build_entry` checks each and
    names the part and the argument when one is wrong.

    Typed as ``add()`` documents them, but checked anyway: a car file is Python written by hand, and a wrong value
    here should be one clear line at ``add()``, not a surprise on the first tick. The defaults are ``add()``'s."""

    #: the part's unique name in the vehicle (reports, errors)
    name: str
    inputs: Sequence[str | None] | None = ()
    outputs: Sequence[str] | None = ()
    threaded: bool = False
    run_condition: str | None = None
    executor: bool = False
    on_error: OnError = "stop"
    shutdown_timeout: float = 2.0
    timeout: float | None = None
    #: ``None``: decided from the part (``safe_state_sync``, or one of Donkeycar's actuator classes)
    actuator: bool | None = None
    pipelined: bool = False
    trigger: str | None = None
    react: bool = False


@dataclass(frozen=True, slots=True)
class BesideTicks:
    """What runs for a part outside its place in the tick, decided at ``add()``: its background work
    (``update()``), whether it is pipelined (and on which input's new values it starts), and whether it also reacts
    to what a pipelined part or a push source publishes (``asyncdonkey.core.pipeline``)."""

    background: Background = Background.NONE
    pipelined: bool = False
    #: a pipelined part's input whose new values start it (``None``: it starts at its place in the tick)
    trigger: str | None = None
    react: bool = False


@dataclass(frozen=True, slots=True)
class ShutdownPlan:
    """How a part is shut down at the end of a drive (``asyncdonkey.core.shutdown``): its ``shutdown`` method
    (``None``: it has none), whether that takes a ``timeout`` keyword, and the seconds it is allowed."""

    fn: Callable[..., Any] | None
    takes_timeout: bool
    timeout: float


@dataclass(frozen=True, slots=True, eq=False, kw_only=True)
class Entry:
    """One part as ``add()`` planned it: how to call it, read its inputs and store its outputs.

    Frozen: fixed at ``add()`` and never written while the car drives. A drive keeps what it learns about a part
    (errors, timings, latency recorder, pipeline kicks, guard, checked stores) in a
    :class:`~asyncdonkey.core.partrun.PartRun` of its own, so the next drive starts from the same plan; the
    frozen dataclass makes a write to the plan an error instead of a leak from one drive into the next.

    Compared by identity (``eq=False``): an entry is one ``add()`` call, and two adds of the same part are two
    entries (a part need not be hashable or comparable). The tick never reads an entry: it reads the copies on
    the drive's runs (``core/partrun.py``), so the frozen dataclass's construction cost is paid once, at ``add()``.
    """

    part: Any
    name: str
    inputs: tuple[str | None, ...]
    outputs: tuple[str, ...]
    run_condition: str | None
    on_error: OnError
    #: an awaited call's bound in seconds (``None``: unbounded)
    timeout: float | None
    #: a sync ``run`` offloaded to the drive's worker pool (``executor=True``, or pipelined)
    executor: bool
    #: the tick awaits the call (an ``async`` run, or an offloaded one); ``is_sync_inline`` is its opposite: the
    #: call holds the loop thread until it returns
    awaits: bool
    is_sync_inline: bool
    #: the part's own method (``run`` or ``run_threaded``), and what the tick calls (offloaded, bounded)
    fn: Callable[..., Any]
    call: Callable[..., Any]
    #: ``args()``: the inputs' values (and ages) as the call takes them
    args: Callable[[], Sequence[Any]]
    #: ``store(result, args, now)``: the outputs with their write time and origin (``None``: no outputs)
    store: Callable[[Any, Sequence[Any], float], None] | None
    #: pipelined parts: the origin of the inputs as they are now (taken when the worker reads them; ``None`` for a
    #: part without inputs, a source sensed when it reads them) and a store that writes the outputs with a given
    #: origin (the inputs may have moved on meanwhile)
    input_origin: Callable[[], float] | None
    store_fixed: Callable[[Any, float, float], None] | None
    #: shut down in the first, safe-state phase
    actuator: bool
    beside: BesideTicks
    shutdown: ShutdownPlan


def build_entry(
    mem: Memory, part: Any, options: PartOptions, offload: Callable[[Callable[..., Any]], Callable[..., Any]]
) -> Entry:
    """Validate one ``Vehicle.add`` call (``options``) and prepare its :class:`Entry`; errors name the part and
    argument. ``offload(fn)`` is how an ``executor=True`` part's calls reach the drive's worker pool."""
    o = options
    name = o.name
    where = f"Vehicle.add({name})"
    ins = _channel_list(o.inputs, "inputs", where, none_ok=True)
    outs = _channel_list(o.outputs, "outputs", where)
    threaded, executor, pipelined, timeout = o.threaded, o.executor, o.pipelined, o.timeout
    _check_options(where, ins, outs, threaded, executor, o.run_condition, o.on_error, o.shutdown_timeout, timeout)
    _check_pipelining(where, ins, threaded, pipelined, o.trigger, o.react, o.actuator)

    async_update = inspect.iscoroutinefunction(getattr(part, "update", None))
    fn, method = _run_method(part, name, where, threaded, async_update)
    is_coro = inspect.iscoroutinefunction(fn)
    if executor and is_coro:
        raise PartSpecError(f"{where}: executor=True is for a sync {method}(); {name}.{method} is async")
    if pipelined and not is_coro:
        executor = True  # a pipelined sync part computes in a worker thread, never on the loop thread
    awaits = is_coro or executor
    if timeout is not None and not awaits:
        raise PartSpecError(
            f"{where}: timeout applies to awaited parts (async {method}() or executor=True); a sync {method}() "
            f"running on the loop thread cannot be interrupted. Add it with executor=True to bound it"
        )
    _check_arity(fn, len(ins), where, method)

    bound = None if timeout is None else float(timeout)
    call = offload(fn) if executor else fn
    origin_fn = getattr(part, "output_origin", None)
    return Entry(
        part=part,
        name=name,
        inputs=ins,
        outputs=outs,
        run_condition=o.run_condition,
        on_error=o.on_error,
        timeout=bound,
        executor=executor,
        awaits=awaits,
        is_sync_inline=not awaits,
        fn=fn,  # the part's own method: a guarded executor part's calls are offloaded by its guard, which sees them end
        call=with_timeout(call, bound, name) if bound is not None else call,
        args=_arg_getter(mem, ins),
        store=_storer(mem, name, part, ins, outs, origin_fn if callable(origin_fn) else None),
        input_origin=_input_origin(mem, ins) if _input_channels(ins) else None,
        store_fixed=_fixed_storer(mem, name, outs),
        actuator=_is_actuator(part, o.actuator),
        beside=BesideTicks(background_of(threaded, async_update), pipelined, o.trigger, o.react),
        shutdown=_shutdown_plan(part, o.shutdown_timeout),
    )


def _is_actuator(part: Any, said: bool | None) -> bool:
    """``actuator=None`` decides from the part: it has ``safe_state_sync``, or it is one of Donkeycar's actuators."""
    if said is not None:
        return said
    return callable(getattr(part, "safe_state_sync", None)) or type(part).__module__.startswith(
        _DONKEYCAR_ACTUATOR_MODULES
    )


def _shutdown_plan(part: Any, timeout: float) -> ShutdownPlan:
    shutdown = getattr(part, "shutdown", None)
    fn = shutdown if callable(shutdown) else None
    return ShutdownPlan(fn, fn is not None and _accepts_keyword(fn, "timeout"), float(timeout))


def _check_options(
    where: str,
    ins: tuple[str | None, ...],
    outs: tuple[str, ...],
    threaded: Any,
    executor: Any,
    run_condition: Any,
    on_error: Any,
    shutdown_timeout: Any,
    timeout: Any,
) -> None:
    """The options every part has, each refused with a message naming the part and the argument."""
    for o in outs:
        if o.endswith(AGE_SUFFIX):
            raise PartSpecError(f"{where}: output {o!r} ends in {AGE_SUFFIX!r}, which is for inputs only")
    if type(threaded) is not bool:
        raise PartSpecError(f"{where}: threaded must be True or False, got {threaded!r}")
    if type(executor) is not bool:
        raise PartSpecError(f"{where}: executor must be True or False, got {executor!r}")
    if run_condition is not None and (not isinstance(run_condition, str) or not run_condition):
        raise PartSpecError(f"{where}: run_condition must be a channel name (str), got {run_condition!r}")
    if on_error not in ("stop", "continue"):
        raise PartSpecError(f"{where}: on_error must be 'stop' or 'continue', got {on_error!r}")
    if not _positive_finite(shutdown_timeout):
        raise PartSpecError(f"{where}: shutdown_timeout must be a positive number of seconds, got {shutdown_timeout!r}")
    if timeout is not None and not _positive_finite(timeout):
        raise PartSpecError(f"{where}: timeout must be a positive number of seconds or None, got {timeout!r}")


def _check_pipelining(
    where: str, ins: tuple[str | None, ...], threaded: Any, pipelined: Any, trigger: Any, react: Any, actuator: Any
) -> None:
    """The options of pipelined and reacting parts, and ``actuator``, checked together (they exclude each other)."""
    if type(pipelined) is not bool:
        raise PartSpecError(f"{where}: pipelined must be True or False, got {pipelined!r}")
    if type(react) is not bool:
        raise PartSpecError(f"{where}: react must be True or False, got {react!r}")
    if trigger is not None:
        if not pipelined:
            raise PartSpecError(f"{where}: trigger={trigger!r} starts a pipelined part; add it with pipelined=True")
        if trigger not in ins:
            raise PartSpecError(f"{where}: trigger {trigger!r} must be one of the part's inputs {list(ins)}")
    if pipelined and threaded:
        raise PartSpecError(f"{where}: a pipelined part runs in its own worker; threaded=True does not apply")
    if pipelined and react:
        raise PartSpecError(f"{where}: react=True is for parts downstream of a pipelined part, not the part itself")
    if actuator is not None and type(actuator) is not bool:
        raise PartSpecError(f"{where}: actuator must be True, False or None (decide from the part), got {actuator!r}")


def _run_method(part: Any, name: str, where: str, threaded: bool, async_update: bool) -> tuple[Any, str]:
    """The method each tick calls (``run``, or ``run_threaded`` for a threaded part) and its name."""
    if threaded:
        update = getattr(part, "update", None)
        if update is None or not callable(update):
            raise PartSpecError(f"{where}: threaded=True needs an update() method, {name} has none")
        fn = getattr(part, "run_threaded", None)
        method = "run_threaded"
        if fn is None and async_update:
            fn, method = getattr(part, "run", None), "run"
        if fn is None or not callable(fn):
            raise PartSpecError(f"{where}: threaded=True needs a run_threaded() method, {name} has none")
        return fn, method
    fn = getattr(part, "run", None)
    if fn is None or not callable(fn):
        raise PartSpecError(
            f"{where}: a part needs a run() method (or threaded=True with update() and run_threaded()); {name} has none"
        )
    return fn, "run"


# ------------------------------------------------------------------------------------------------ inputs
def _all_values(ins: tuple[str | None, ...]) -> TypeGuard[tuple[str, ...]]:
    """Every input is a channel whose value is read as it is (no ``None``, no ``@age``): the plain getters apply."""
    return not any(i is None or i.endswith(AGE_SUFFIX) for i in ins)


def _arg_getter(mem: Memory, ins: tuple[str | None, ...]) -> Callable[[], Sequence[Any]]:
    d = mem.d
    if not ins:
        empty: tuple[Any, ...] = ()
        return lambda: empty
    if _all_values(ins):
        dget = d.get
        if len(ins) == 1:
            (k,) = ins
            return lambda: (dget(k),)
        return lambda: list(map(dget, ins))
    origins = mem.origins
    plan = tuple(
        (None, False) if i is None else (i[: -len(AGE_SUFFIX)], True) if i.endswith(AGE_SUFFIX) else (i, False)
        for i in ins
    )

    def get_with_ages() -> list[Any]:
        now = mem._now()
        return [None if k is None else (now - origins.get(k, now - _INF)) if is_age else d.get(k) for k, is_age in plan]

    return get_with_ages


# ----------------------------------------------------------------------------------------------- outputs
def _storer(
    mem: Memory,
    name: str,
    part: Any,
    ins: tuple[str | None, ...],
    outs: tuple[str, ...],
    stated: Callable[[], float | None] | None,
) -> Callable[[Any, Sequence[Any], float], None] | None:
    """``store(result, args, now)``: write the outputs with their write time and origin (module docstring).

    Which case of the rule applies is decided here, once: a source or a part that states its origin, a declared
    selector, a part with one input channel (its outputs have that channel's origin), or any other part (the
    oldest of its inputs' origins, one ``min`` per call, and the in-place check of an output that is a mutable
    input object).
    """
    if not outs:
        return None
    sources = _input_channels(ins)
    unpack = _unpacker(name, outs)
    if stated is not None or not sources:
        return _stated_storer(mem, outs, unpack, _input_origin(mem, ins) if sources else None, stated)
    declared = declared_sources(part, len(ins), len(outs))
    if declared is not None:
        return _selector_storer(mem, name, ins, outs, unpack, declared)
    if len(sources) == 1:
        # one input channel: a value made from it, passed through or written into in place has only its
        # sensing behind it
        return _one_input_storer(mem, outs, unpack, sources[0])
    return _oldest_storer(mem, ins, outs, unpack)


def _stated_storer(
    mem: Memory,
    outs: tuple[str, ...],
    unpack: Callable[[Any], Any],
    inherited: Callable[[], float] | None,
    stated: Callable[[], float | None] | None,
) -> Callable[[Any, Sequence[Any], float], None]:
    """Sources (``inherited`` is ``None``) and parts that state their origin: one origin for every output."""
    d, stamps, origins = mem.d, mem.stamps, mem.origins

    def origin_of(now: float) -> float:
        if stated is not None:
            o = stated()
            if o is not None:
                return o
        return now if inherited is None else inherited()

    if len(outs) == 1:
        (k1,) = outs

        def store_stated_one(value: Any, args: Sequence[Any], now: float) -> None:
            d[k1] = value
            stamps[k1] = now
            o = origin_of(now)
            if o > _NEVER:
                origins[k1] = o
            else:
                origins.pop(k1, None)

        return store_stated_one

    def store_stated_many(values: Any, args: Sequence[Any], now: float) -> None:
        # An output of None among others holds nothing sensed: no origin, however young the others are (a
        # remote pilot's subscriber returns (None, None) until its first command arrives; dated by the tick,
        # that command-less throttle looked a few ms old).
        values = unpack(values)
        o = origin_of(now)
        for k, v in zip(outs, values, strict=False):
            d[k] = v
            stamps[k] = now
            if o > _NEVER and v is not None:
                origins[k] = o
            else:
                origins.pop(k, None)

    return store_stated_many


def _one_input_storer(
    mem: Memory, outs: tuple[str, ...], unpack: Callable[[Any], Any], k0: str
) -> Callable[[Any, Sequence[Any], float], None]:
    """A part reading one channel: every output gets that channel's origin (none if it has none)."""
    d, stamps, origins = mem.d, mem.stamps, mem.origins
    oget = origins.get
    if len(outs) == 1:
        (k1,) = outs

        def store_one_from_one(value: Any, args: Sequence[Any], now: float) -> None:
            d[k1] = value
            stamps[k1] = now
            t = oget(k0)
            if t is not None:
                origins[k1] = t
            else:
                origins.pop(k1, None)

        return store_one_from_one

    def store_many_from_one(values: Any, args: Sequence[Any], now: float) -> None:
        values = unpack(values)
        t = oget(k0)
        for k, v in zip(outs, values, strict=False):
            d[k] = v
            stamps[k] = now
            if t is not None:
                origins[k] = t
            else:
                origins.pop(k, None)

    return store_many_from_one


def _oldest_storer(
    mem: Memory, ins: tuple[str | None, ...], outs: tuple[str, ...], unpack: Callable[[Any], Any]
) -> Callable[[Any, Sequence[Any], float], None]:
    """A part reading several channels, not declaring what it selected: every output gets the oldest origin of
    its inputs. An output that is a mutable input object may hold what the part wrote into it: every channel
    holding that object is aged to that origin too (:func:`_in_place_ager`)."""
    d, stamps, origins = mem.d, mem.stamps, mem.origins
    oldest = _input_origin(mem, ins)
    age_holders = _in_place_ager(mem, ins)
    immutable = _IMMUTABLE_TYPES
    if len(outs) == 1:
        (k1,) = outs

        def store_oldest_one(value: Any, args: Sequence[Any], now: float) -> None:
            o = oldest()
            d[k1] = value
            stamps[k1] = now
            if o > _NEVER:
                origins[k1] = o
            else:
                origins.pop(k1, None)
            if type(value) not in immutable:
                age_holders(value, args, o)

        return store_oldest_one

    def store_oldest_many(values: Any, args: Sequence[Any], now: float) -> None:
        values = unpack(values)
        o = oldest()
        if o == _NEVER:  # nothing sensed behind any input: no origin, and nothing to age
            for k, v in zip(outs, values, strict=False):
                d[k] = v
                stamps[k] = now
                origins.pop(k, None)
            return
        for k, v in zip(outs, values, strict=False):
            d[k] = v
            stamps[k] = now
            origins[k] = o
            if type(v) not in immutable:
                age_holders(v, args, o)

    return store_oldest_many


def _in_place_ager(mem: Memory, ins: tuple[str | None, ...]) -> Callable[[Any, Sequence[Any], float], None]:
    """``age(value, args, origin)``: if ``value`` is one of the input objects and can be written into (an array,
    a list, a dict), every channel holding it gets ``origin`` when it is younger.

    Why: a part that fuses an old IMU sample into the camera's frame in place (``np.add(img, imu, out=img);
    return img``) changes what ``cam/image_array`` holds, and every other channel holding that frame, not only its
    own output. Identity says the object is shared, not whether it was written into: a part returning an input
    array as it is ages its holders too (the safe side; a selector that only picks declares, :mod:`.selectors`).
    Not seen: an input written into and not returned, and an object held inside another (a list in a dict).
    """
    d, origins = mem.d, mem.origins
    valued = tuple(i for i, k in enumerate(ins) if k is not None and not k.endswith(AGE_SUFFIX))

    def age(value: Any, args: Sequence[Any], origin: float) -> None:
        if value is None or origin == _NEVER:
            return
        for i in valued:
            if args[i] is value:
                break
        else:
            return
        if _immutable(value):
            return
        for k, held in d.items():
            if held is value:
                t = origins.get(k)
                if t is not None and t > origin:
                    origins[k] = origin

    return age


def _selector_storer(
    mem: Memory,
    name: str,
    ins: tuple[str | None, ...],
    outs: tuple[str, ...],
    unpack: Callable[[Any], Any],
    declared: OutputSources,
) -> Callable[[Any, Sequence[Any], float], None]:
    """A declared selector (:mod:`.selectors`): each output gets the oldest origin of the inputs its declaration
    names for this call (``None``: of all inputs). Each distinct declaration is checked and turned into channel
    names once, then looked up (a drive mode returns one of three)."""
    d, stamps, origins = mem.d, mem.stamps, mem.origins
    oget = origins.get
    plans: dict[Any, tuple[str | tuple[str, ...], ...]] = {}
    n = len(outs)
    make_plan = _selection_plan(name, ins, outs)

    def store_selected(values: Any, args: Sequence[Any], now: float) -> None:
        picked = declared(*args)
        try:
            plan = plans[picked]
        except (KeyError, TypeError):  # new, or unhashable (a list): checked each time
            plan = make_plan(picked)
            if len(plans) < 64:
                try:
                    plans[picked] = plan
                except TypeError:
                    pass
        values = (values,) if n == 1 else unpack(values)
        for k, v, group in zip(outs, values, plan, strict=False):
            d[k] = v
            stamps[k] = now
            o = oget(group) if type(group) is str else min(map(oget, group, _INFS), default=None)
            if o is not None and o < _INF:
                origins[k] = o
            else:
                origins.pop(k, None)

    return store_selected


def _selection_plan(
    name: str, ins: tuple[str | None, ...], outs: tuple[str, ...]
) -> Callable[[Any], tuple[str | tuple[str, ...], ...]]:
    """``plan(declaration)``: for each output, the channel (or the tuple of channels) whose origin dates it; a
    declaration that is not one entry per output, each an input index, a tuple of them or ``None``, raises naming
    the part."""
    every = _input_channels(ins)
    channel = tuple(None if k is None else k.removesuffix(AGE_SUFFIX) for k in ins)

    def bad(picked: Any, why: str) -> PartSpecError:
        return PartSpecError(
            f"{name}: output_sources() returned {picked!r}, {why}; expected one entry per output {list(outs)}: an "
            f"input index 0..{len(ins) - 1}, a tuple of them, or None"
        )

    def channels_of(picked: Any, src: Any) -> str | tuple[str, ...]:
        if src is None:
            return every
        group = src if isinstance(src, tuple) else (src,)
        for i in group:
            if type(i) is not int or not 0 <= i < len(ins):
                raise bad(picked, f"with {i!r} not an input index")
        chans = tuple(k for i in group if (k := channel[i]) is not None)
        return chans[0] if len(chans) == 1 else chans

    def plan(picked: Any) -> tuple[str | tuple[str, ...], ...]:
        try:
            entries = tuple(picked)
        except TypeError:
            raise bad(picked, "not a sequence") from None
        if len(entries) != len(outs):
            raise bad(picked, f"{len(entries)} entries for {len(outs)} outputs")
        return tuple(channels_of(picked, src) for src in entries)

    return plan


def _put_origin(origins: dict[str, float], k: str, o: float) -> None:
    """Write channel ``k``'s origin; ``_NEVER`` (nothing sensed behind the value) leaves it without one."""
    if o > _NEVER:
        origins[k] = o
    else:
        origins.pop(k, None)


def _unpacker(name: str, outs: tuple[str, ...]) -> Callable[[Any], Any]:
    """``unpack(values)``: check that a result unpacks into ``outs`` (fewer values is an error naming the
    channels; extra values are ignored with a warning once, as Donkeycar ignores them)."""
    n = len(outs)
    warned = False

    def unpack(values: Any) -> Any:
        nonlocal warned
        try:
            count = len(values)
        except TypeError:
            raise OutputCountError(
                f"returned {type(values).__name__} for {n} outputs {list(outs)}; expected a tuple or list of {n} values"
            ) from None
        if count < n:
            raise OutputCountError(f"returned {count} values for {n} outputs {list(outs)}")
        if count > n and not warned:
            # Donkeycar stores the first N and ignores the rest; parts written for it rely on that
            warned = True
            logger.warning(
                "part %r returned %d values for its %d outputs %s: storing the first %d, ignoring the rest "
                "(warned once)",
                name,
                count,
                n,
                list(outs),
                n,
            )
        return values

    return unpack


def _input_channels(ins: tuple[str | None, ...]) -> tuple[str, ...]:
    """The channels a part reads (an ``@age`` input reads its channel's origin), each once, in order."""
    return tuple(dict.fromkeys(k.removesuffix(AGE_SUFFIX) for k in ins if k is not None))


def _input_origin(mem: Memory, ins: tuple[str | None, ...]) -> Callable[[], float]:
    """``origin()``: the oldest origin among the part's input channels that have one, ``_NEVER`` if none has.

    Every input counts, whatever wrote it and whenever: a channel's origin is the truth about the value it holds,
    so the oldest of them is never younger than the data the part could have used. A channel read only for its
    age (``"x@age"``) counts too: the part may compute with that age (a gate passing a command while the frame is
    young), and counting it can only make the output older. A channel never written has no origin and no data:
    it does not count.
    """
    oget = mem.origins.get
    sources = _input_channels(ins)
    if len(sources) == 1:
        (k0,) = sources
        return lambda: oget(k0, _NEVER)
    infs = (_INF,) * len(sources)

    def origin() -> float:
        t = min(map(oget, sources, infs))
        return t if t < _INF else _NEVER

    return origin


def _immutable(value: Any) -> bool:
    """Can ``value`` not have been written into in place? Decided once per type; a tuple's (or frozenset's)
    items are looked at each time (an array inside a tuple can be written into)."""
    tp = type(value)
    if tp in _IMMUTABLE_TYPES:
        return True
    if tp in _CONTAINERS:
        return all(map(_immutable, value))
    kind = _TYPE_KIND.get(tp)
    if kind is None:
        kind = _TYPE_KIND[tp] = _immutability_of(tp)
        if kind:
            _IMMUTABLE_TYPES.add(tp)
    return kind


def _immutability_of(tp: type) -> bool:
    """``True`` for types whose instances cannot change (enums, numpy scalars), ``False`` for everything else
    (lists, dicts, arrays, any other object: it might be written into)."""
    if issubclass(tp, enum.Enum):
        return True
    np = sys.modules.get("numpy")  # not imported yet: no value can be a numpy scalar
    return np is not None and issubclass(tp, np.generic) and not issubclass(tp, np.void)


def _fixed_storer(mem: Memory, name: str, outs: tuple[str, ...]) -> Callable[[Any, float, float], None] | None:
    """``store(result, origin, now)``: every output gets ``origin`` (a pipelined part's inputs, as read; ``_NEVER``:
    none)."""
    if not outs:
        return None
    d, stamps, origins = mem.d, mem.stamps, mem.origins
    n = len(outs)
    if n == 1:
        (k1,) = outs

        def store_one(value: Any, origin: float, now: float) -> None:
            d[k1] = value
            stamps[k1] = now
            _put_origin(origins, k1, origin)

        return store_one

    unpack = _unpacker(name, outs)

    def store_many(values: Any, origin: float, now: float) -> None:
        values = unpack(values)
        for k, v in zip(outs, values, strict=False):
            d[k] = v
            stamps[k] = now
            _put_origin(origins, k, origin)

    return store_many


# ------------------------------------------------------------------------------------------ checked mode
#: a store, either kind: ``store(result, args, now)`` or ``store_fixed(result, origin, now)``
Store = Callable[[Any, Any, float], None]


def checked_store(store: Store | None, name: str, outs: tuple[str, ...], contracts: Contracts) -> Store | None:
    """``store`` behind a check of each output against its channel's contract (checked mode), or ``store`` itself
    when none of ``outs`` has a contract (nothing to check, nothing added).

    Why a wrapper, made when a drive starts: contracts can be declared after ``add()``, and a car that is not
    checked must not pay a per-tick ``if checked`` for it. A value that breaks its contract raises
    :class:`ContractViolation` naming the part, the channel, the value and what was expected *before anything is
    stored*, so the tick handles it like any part error (``on_error``) and no output of that call reaches Memory.
    The values are checked, never replaced: a checked car stores what an unchecked one does (the same objects,
    which the provenance rule's in-place check relies on). ``None`` passes: it is Donkeycar's "no value yet"
    for one of several outputs (a single output of ``None`` is never stored at all).
    """
    if store is None:
        return None
    plan = tuple((i, k, c) for i, k in enumerate(outs) if (c := contracts.get(k)) is not None)
    if not plan:
        return store
    if len(outs) == 1:
        ((_, k1, c1),) = plan
        check1 = c1.check

        def store_checked_one(value: Any, a: Any, now: float) -> None:
            try:
                check1(value)
            except ContractViolation as exc:
                raise _violation(name, k1, c1, exc) from None
            store(value, a, now)

        return store_checked_one

    checks = tuple((i, k, c, c.check) for i, k, c in plan)

    def store_checked_many(values: Any, a: Any, now: float) -> None:
        try:
            for i, k, c, check in checks:
                v = values[i]
                if v is not None:
                    try:
                        check(v)
                    except ContractViolation as exc:
                        raise _violation(name, k, c, exc) from None
        except (TypeError, IndexError, KeyError):
            pass  # not a sequence of enough values: the store itself says so (OutputCountError)
        store(values, a, now)

    return store_checked_many


def _violation(name: str, channel: str, contract: Contract, exc: ContractViolation) -> ContractViolation:
    return ContractViolation(channel, exc.reason, f"{exc.detail} (expected {contract.describe()})", name)


# --------------------------------------------------------------------------------------------- helpers
def with_timeout(call: Callable[..., Any], timeout: float, name: str) -> Callable[..., Any]:
    """Wrap an awaited call so that it is cancelled after ``timeout`` seconds (a :class:`PartTimeoutError`)."""

    async def bounded(*args: Any) -> Any:
        try:
            async with asyncio.timeout(timeout):
                return await call(*args)
        except TimeoutError:
            raise PartTimeoutError(f"did not return within its timeout of {timeout:g} s (cancelled)") from None

    return bounded


def make_offload(get_executor: Callable[[], concurrent.futures.Executor]) -> Callable[..., Any]:
    """``offload(fn)`` → a function returning the future of ``fn(*args)`` run in the vehicle's worker pool."""

    def offload(fn: Callable[..., Any]) -> Callable[..., Any]:
        def offloaded(*args: Any) -> asyncio.Future[Any]:
            return asyncio.get_running_loop().run_in_executor(get_executor(), fn, *args)

        return offloaded

    return offload


def _positive_finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _channel_list(value: Any, arg: str, where: str, none_ok: bool = False) -> tuple[Any, ...]:
    """The channel names of ``inputs``/``outputs``; ``None`` is allowed as an input (it is always ``None``,
    as in Donkeycar, whose templates pass ``inputs=["throttle", "steering", None]``)."""
    if value is None:
        return ()
    if isinstance(value, str):
        raise PartSpecError(
            f"{where}: {arg} must be a list of channel names, got the string {value!r}; did you mean [{value!r}]?"
        )
    if not isinstance(value, list | tuple):
        raise PartSpecError(f"{where}: {arg} must be a list or tuple of channel names, got {type(value).__name__}")
    for i, v in enumerate(value):
        if v is None and none_ok:
            continue
        if not isinstance(v, str) or not v:
            raise PartSpecError(f"{where}: {arg}[{i}] must be a non-empty channel name (str), got {v!r}")
    return tuple(value)


def _check_arity(fn: Callable[..., Any], n: int, where: str, method: str) -> None:
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return
    try:
        sig.bind(*([None] * n))
    except TypeError as exc:
        raise PartSpecError(f"{where}: {method}() cannot take the {n} input(s) given: {exc}") from None


def _accepts_keyword(fn: Callable[..., Any], name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    p = params.get(name)
    if p is not None and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
        return True
    return any(q.kind is q.VAR_KEYWORD for q in params.values())
