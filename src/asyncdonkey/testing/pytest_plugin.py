"""pytest plugin (entry point ``pytest11``): the virtual clock and checked mode, each for the tests that ask.

Installing asyncdonkey loads this plugin into every pytest session of every project in that environment, so
it changes nothing for a project, or a test, that did not ask for what it offers: it registers its markers, its
``asyncdonkey_checked`` ini option and its ``virtual_clock`` fixture, and that is all.

**The virtual clock.** Opt in per test, class or module, together with pytest-asyncio's own marker::

    @pytest.mark.asyncio
    @pytest.mark.virtual_clock
    async def test_hours_of_driving(): ...

or ask for the ``virtual_clock`` fixture (it returns the running :class:`VirtualClockLoop`), or select the
factory by name: ``@pytest.mark.asyncio(loop_factories=["virtual_clock"])``.

Loop selection uses pytest-asyncio's ``pytest_asyncio_loop_factories`` hook (pytest-asyncio ≥ 1.4). As soon as
any plugin implements that hook, pytest-asyncio calls it for every asyncio test, takes the first answer
(``firstresult``), parametrizes the test by it (a ``loop_scope="session"`` test then moves: tests sharing a
parametrized higher-scoped fixture are grouped), and skips a test whose ``loop_factories`` names a factory
missing from that answer. So the implementation is not registered at all until the first collected test asks
for the virtual clock (a project that never does keeps pytest-asyncio's own path, test order and loops; in one
that does, the asyncio tests collected before that one stay unparametrized, so a session-scoped loop is made anew
once between them and the later ones), and once registered it is a *wrapper* around all the others:

* a test that did not opt in gets the other implementations' answer untouched. Only when no other
  implementation exists is there nothing to pass on; then it answers ``{"asyncio": asyncio.new_event_loop}``,
  the loop pytest-asyncio makes without any hook, and a ``loop_factories`` selection fails as it would with
  no hook at all;
* a test that opted in by the marker or the fixture (and named no factories) gets only ``virtual_clock``;
* a test whose ``loop_factories`` names ``virtual_clock`` gets the others' factories plus ``virtual_clock``
  (plus ``asyncio`` when there are no others), so it can run on several loops.

The hook is declared ``optionalhook=True`` so this plugin loads harmlessly where pytest-asyncio is absent.

**Checked mode** (opt-in). With ``asyncdonkey_checked = true`` in a project's pytest ini, or for one test,
class or module with ``@pytest.mark.asyncdonkey_checked``, every :class:`~asyncdonkey.loop.Vehicle` that does not
say otherwise drives in checked mode: each part output is checked against its channel's contract and a value that
breaks it fails the part that wrote it (``asyncdonkey.contracts``), so a test finds the part that writes a NaN
throttle, not the actuator three parts later. Off by default, as on the car: a project's fake camera returning
float64 zeros drives its car, and its tests pass, until the project asks for the contracts to be enforced.
Only asyncdonkey's own default is changed (:attr:`Vehicle.checked_by_default`, a class attribute, for the
session or the test, put back after it): nothing is patched or set in the environment.
``@pytest.mark.asyncdonkey_checked(False)`` turns it off for a test of a project that opted in;
``Vehicle(checked=...)`` and ``run(checked=...)`` still decide for themselves.
"""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Generator, Mapping
from typing import Any

import pytest

from ..clock.virtual_loop import VirtualClockError, VirtualClockLoop, virtual_loop_factory
from ..loop import Vehicle

FACTORY_NAME = "virtual_clock"
#: virtual seconds a test may run unless its marker says otherwise (``budget_s=None``: no limit): a test
#: waiting for something that never comes beside a periodic task fails in a second instead of running away
TEST_BUDGET_S = 3600.0
_DEFAULT_NAME = "asyncio"
#: the ini option and the marker that turn checked mode on (or, the marker with False, off) for a project or a test
CHECKED_OPTION = CHECKED_MARKER = "asyncdonkey_checked"
#: the name the loop-factories hook implementation is registered under, once a test asks for the virtual clock
FACTORIES_PLUGIN = "asyncdonkey-virtual-clock-factories"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addini(
        CHECKED_OPTION,
        "drive asyncdonkey Vehicles in checked mode during tests (each part output checked against its channel's "
        "contract, a value that breaks it fails the part); default false",
        type="bool",
        default=False,
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "virtual_clock(backend='asyncio', autojump_threshold=0.001, budget_s=3600, **loop_kwargs): run this "
        "asyncio test on asyncdonkey's VirtualClockLoop (time jumps to the next timer when every task is waiting)",
    )
    config.addinivalue_line(
        "markers",
        f"{CHECKED_MARKER}(on=True): drive asyncdonkey Vehicles in this test in checked mode (part outputs checked "
        "against their channels' contracts) or, with False, not (Vehicle(checked=...) and run(checked=...) still "
        "decide for themselves)",
    )
    if config.getini(CHECKED_OPTION):  # not opted in: asyncdonkey's default is left as it is
        before = Vehicle.checked_by_default
        Vehicle.checked_by_default = True
        config.add_cleanup(lambda: setattr(Vehicle, "checked_by_default", before))


def _checked_by_marker(item: pytest.Item) -> bool | None:
    """What the test's ``asyncdonkey_checked`` marker asks (``None``: it has none)."""
    marker = item.get_closest_marker(CHECKED_MARKER)
    if marker is None:
        return None
    on = marker.args[0] if marker.args else marker.kwargs.get("on", True)
    if type(on) is not bool:
        raise pytest.UsageError(f"{item.nodeid}: {CHECKED_MARKER}(on) takes True or False, got {on!r}")
    return on


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Generator[None, object, object]:
    """A test marked ``asyncdonkey_checked`` (or ``(False)``) runs, fixtures included, with that default."""
    on = _checked_by_marker(item)
    if on is None:
        return (yield)
    before = Vehicle.checked_by_default
    Vehicle.checked_by_default = on
    try:
        return (yield)
    finally:
        Vehicle.checked_by_default = before


# ------------------------------------------------------------------------------------------- the virtual clock
def _selected(item: pytest.Item) -> list[str] | None:
    """The factory names the test's ``asyncio`` marker selects (``loop_factories``), or ``None``."""
    marker = item.get_closest_marker("asyncio")
    names = marker.kwargs.get("loop_factories") if marker is not None else None
    if names is None or isinstance(names, str):
        return None if names is None else [names]
    return list(names)


def _uses_our_fixture(item: pytest.Item) -> bool:
    """Whether the test requests this plugin's ``virtual_clock`` fixture (a project's own fixture of that name,
    which overrides ours, does not opt its tests in)."""
    if FACTORY_NAME not in getattr(item, "fixturenames", ()):
        return False
    info = getattr(item, "_fixtureinfo", None)
    defs = info.name2fixturedefs.get(FACTORY_NAME, ()) if info is not None else ()
    return bool(defs) and getattr(defs[-1].func, "__module__", None) == __name__


def _asks_for_virtual_clock(item: pytest.Item) -> bool:
    selected = _selected(item)
    return (
        item.get_closest_marker("virtual_clock") is not None
        or (selected is not None and FACTORY_NAME in selected)
        or _uses_our_fixture(item)
    )


def _others_implement(item: pytest.Item) -> bool:
    """Whether a plugin other than this one answers the hook for ``item`` (wrappers do not answer)."""
    impls = item.ihook.pytest_asyncio_loop_factories.get_hookimpls()
    return any(not (impl.wrapper or impl.hookwrapper) for impl in impls)


def _virtual_factory(item: pytest.Item) -> Any:
    marker = item.get_closest_marker("virtual_clock")
    kwargs = dict(marker.kwargs) if marker is not None else {}
    backend = kwargs.pop("backend", "asyncio")
    if backend != "asyncio":
        try:
            virtual_loop_factory(backend)
        except VirtualClockError as exc:
            raise pytest.UsageError(f"{item.nodeid}: {exc}") from None
    kwargs.setdefault("budget_s", TEST_BUDGET_S)
    try:
        inspect.signature(VirtualClockLoop).bind(**kwargs)
    except TypeError as exc:
        knobs = ", ".join(inspect.signature(VirtualClockLoop).parameters)
        raise pytest.UsageError(f"{item.nodeid}: virtual_clock marker: {exc} (the loop takes: {knobs})") from None
    return virtual_loop_factory(**kwargs)


class _LoopFactories:
    """The ``pytest_asyncio_loop_factories`` implementation, registered by the first test that asks for the
    virtual clock (see the module's docstring): until then pytest-asyncio sees no implementation at all."""

    @pytest.hookimpl(wrapper=True, optionalhook=True)
    def pytest_asyncio_loop_factories(
        self, config: pytest.Config, item: pytest.Item
    ) -> Generator[None, Mapping[str, Any] | None, Mapping[str, Any] | None]:
        answer = yield
        selected = _selected(item)
        if selected is not None and FACTORY_NAME in selected:
            factories = dict(answer) if answer else {_DEFAULT_NAME: asyncio.new_event_loop}
            factories[FACTORY_NAME] = _virtual_factory(item)
            return factories
        by_marker = item.get_closest_marker("virtual_clock") is not None
        if selected is None and (by_marker or _uses_our_fixture(item)):
            return {FACTORY_NAME: _virtual_factory(item)}
        if by_marker:
            raise pytest.UsageError(
                f"{item.nodeid}: marked virtual_clock, but its asyncio marker's loop_factories {selected} do not "
                f"name {FACTORY_NAME!r}"
            )
        # not ours: whatever the project's own implementations said, untouched
        if answer is not None or _others_implement(item):
            return answer
        if selected is not None:
            pytest.fail(
                f"{item.nodeid}: mark.asyncio 'loop_factories' {selected} needs a pytest_asyncio_loop_factories "
                f"hook implementation that provides them (asyncdonkey's plugin provides only {FACTORY_NAME!r})",
                pytrace=False,
            )
        return {_DEFAULT_NAME: asyncio.new_event_loop}


@pytest.hookimpl(wrapper=True)
def pytest_generate_tests(metafunc: pytest.Metafunc) -> Generator[None, None, None]:
    """Registers :class:`_LoopFactories` before pytest-asyncio parametrizes the first test that asks for the
    virtual clock (a wrapper runs before its ``tryfirst`` implementation)."""
    manager = metafunc.config.pluginmanager
    if (
        pytest_asyncio is not None
        and not manager.has_plugin(FACTORIES_PLUGIN)
        and _asks_for_virtual_clock(metafunc.definition)
    ):
        manager.register(_LoopFactories(), name=FACTORIES_PLUGIN)
    return (yield)


try:
    import pytest_asyncio
except ImportError:  # pragma: no cover - the plugin must load without pytest-asyncio
    pytest_asyncio = None

if pytest_asyncio is not None:

    @pytest_asyncio.fixture
    async def virtual_clock() -> VirtualClockLoop:
        """The running :class:`VirtualClockLoop`; requesting this fixture opts the test into virtual time."""
        loop = asyncio.get_running_loop()
        if not isinstance(loop, VirtualClockLoop):
            raise RuntimeError(
                f"the virtual_clock fixture expected a VirtualClockLoop, the test runs on {type(loop).__name__}"
            )
        return loop
