"""pytest plugin (entry point ``pytest11``): run chosen asyncio tests on :class:`VirtualClockLoop`.

Opt in per test, class or module, together with pytest-asyncio's own marker::

    @pytest.mark.asyncio
    @pytest.mark.virtual_clock
    async def test_hours_of_driving(): ...

or ask for the ``virtual_clock`` fixture (it returns the running :class:`VirtualClockLoop`), or select the
factory by name: ``@pytest.mark.asyncio(loop_factories=["virtual_clock"])``.

Loop selection uses pytest-asyncio's ``pytest_asyncio_loop_factories`` hook (pytest-asyncio ≥ 1.4). The hook is
declared ``optionalhook=True`` so this plugin loads harmlessly where pytest-asyncio is absent. Tests that did
not opt in get a single factory that asks the current event loop policy for a new loop, which is what
pytest-asyncio would have done, so installing asyncdonkey changes nothing for them.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from .virtual_loop import VirtualClockError, VirtualClockLoop, virtual_loop_factory

FACTORY_NAME = "virtual_clock"
_DEFAULT_NAME = "asyncio"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "virtual_clock(backend='asyncio', **loop_kwargs): run this asyncio test on asyncdonkey's "
        "VirtualClockLoop (time jumps to the next timer when every task is waiting)",
    )


def _policy_loop() -> asyncio.AbstractEventLoop:
    return asyncio.get_event_loop_policy().new_event_loop()


def _wants_virtual(item: pytest.Item) -> bool:
    if item.get_closest_marker("virtual_clock") is not None:
        return True
    return FACTORY_NAME in getattr(item, "fixturenames", ())


@pytest.hookimpl(optionalhook=True)
def pytest_asyncio_loop_factories(config: pytest.Config, item: pytest.Item) -> dict[str, Any]:
    marker = item.get_closest_marker("virtual_clock")
    kwargs = dict(marker.kwargs) if marker is not None else {}
    backend = kwargs.pop("backend", "asyncio")
    if backend != "asyncio":
        try:
            virtual_loop_factory(backend)
        except VirtualClockError as exc:
            raise pytest.UsageError(f"{item.nodeid}: {exc}") from None
    virtual = virtual_loop_factory(**kwargs)
    asyncio_marker = item.get_closest_marker("asyncio")
    selected = asyncio_marker.kwargs.get("loop_factories") if asyncio_marker is not None else None
    if selected is not None:
        return {FACTORY_NAME: virtual, _DEFAULT_NAME: _policy_loop}
    if _wants_virtual(item):
        return {FACTORY_NAME: virtual}
    return {_DEFAULT_NAME: _policy_loop}


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
