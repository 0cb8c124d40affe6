"""The pytest plugin: opting in by marker, fixture or factory name; everything else untouched."""

import asyncio

import pytest

from asyncdonkey.testing import VirtualClockLoop

pytest_plugins = ["pytester"]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_marker_selects_the_virtual_loop():
    assert isinstance(asyncio.get_running_loop(), VirtualClockLoop)
    await asyncio.sleep(3600)
    assert asyncio.get_running_loop().time() == 3600.0


@pytest.mark.asyncio
async def test_fixture_selects_the_virtual_loop(virtual_clock):
    assert virtual_clock is asyncio.get_running_loop()


@pytest.mark.asyncio(loop_factories=["virtual_clock"])
async def test_factory_name_selects_the_virtual_loop():
    assert isinstance(asyncio.get_running_loop(), VirtualClockLoop)


@pytest.mark.asyncio
async def test_tests_that_did_not_opt_in_run_on_a_normal_loop():
    assert not isinstance(asyncio.get_running_loop(), VirtualClockLoop)


def test_uvloop_backend_marker_is_a_usage_error(pytester):
    pytester.makeini("[pytest]\nasyncio_default_fixture_loop_scope = function\n")
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.asyncio
        @pytest.mark.virtual_clock(backend="uvloop")
        async def test_x():
            pass
        """
    )
    result = pytester.runpytest()  # the plugin is loaded through its pytest11 entry point
    result.stdout.fnmatch_lines(["*uvloop keeps its clock and timers inside libuv*"])
    assert result.ret != 0
