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
@pytest.mark.virtual_clock(autojump_threshold=0.25, budget_s=60, stall_timeout_s=5)
async def test_marker_arguments_reach_the_loop():
    loop = asyncio.get_running_loop()
    assert (loop.autojump_threshold, loop.budget_s, loop.stall_timeout_s) == (0.25, 60, 5)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_test_gets_an_hour_of_virtual_time_by_default():
    assert asyncio.get_running_loop().budget_s == 3600


def test_an_unknown_marker_argument_is_a_usage_error(pytester):
    pytester.makeini("[pytest]\nasyncio_default_fixture_loop_scope = function\n")
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.asyncio
        @pytest.mark.virtual_clock(autojump=0.1)
        async def test_x():
            pass
        """
    )
    result = pytester.runpytest()
    result.stdout.fnmatch_lines(["*virtual_clock marker*autojump*the loop takes: start, autojump_threshold, budget_s*"])
    assert result.ret != 0


@pytest.mark.asyncio
async def test_fixture_selects_the_virtual_loop(virtual_clock):
    assert virtual_clock is asyncio.get_running_loop()


@pytest.mark.asyncio(loop_factories=["virtual_clock"])
async def test_factory_name_selects_the_virtual_loop():
    assert isinstance(asyncio.get_running_loop(), VirtualClockLoop)


@pytest.mark.realtime
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


# ------------------------------------------------------------------ other projects' tests are left alone
PREAMBLE = """
    import asyncio
    import pytest
    from asyncdonkey.testing import VirtualClockLoop

    def loop_kind():
        return type(asyncio.get_running_loop()).__module__.split(".")[0]
"""
UVLOOP_TEST = """
    @pytest.mark.asyncio(loop_factories=["uvloop"])
    async def test_on_uvloop():
        assert loop_kind() == "uvloop"
"""
OTHER_TESTS = """
    @pytest.mark.asyncio
    async def test_plain():
        assert not isinstance(asyncio.get_running_loop(), VirtualClockLoop)
        print("PLAIN_LOOP", loop_kind())

    @pytest.mark.asyncio
    @pytest.mark.virtual_clock
    async def test_opted_in_by_marker():
        assert isinstance(asyncio.get_running_loop(), VirtualClockLoop)

    @pytest.mark.asyncio
    async def test_opted_in_by_fixture(virtual_clock):
        assert virtual_clock is asyncio.get_running_loop()

    @pytest.mark.asyncio(loop_factories=["virtual_clock", "{other}"])
    async def test_both_by_name():
        print("BOTH", loop_kind())
"""

UVLOOP_HOOK = """
    import pytest
    import uvloop

    @pytest.hookimpl({options})
    def pytest_asyncio_loop_factories(config, item):
        return {{"uvloop": uvloop.new_event_loop}}
"""


def _project(pytester, *tests: str) -> None:
    pytester.makeini("[pytest]\nasyncio_default_fixture_loop_scope = function\n")
    pytester.makepyfile(test_other="".join((PREAMBLE, *tests)))


@pytest.mark.realtime
@pytest.mark.parametrize("where", ["-p plugin", "trylast conftest"])
def test_another_projects_uvloop_factory_is_used_and_ours_added_only_when_asked(pytester, where):
    """Their hook registered before ours (``-p``) or called after it (``trylast``) used to lose to ours: the
    uvloop test was skipped as "not available". Now their answer stands for every test that did not ask for
    the virtual clock, whatever the order."""
    _project(pytester, UVLOOP_TEST, OTHER_TESTS.replace("{other}", "uvloop"))
    args = ["-s", "-v"]
    if where == "-p plugin":
        pytester.makepyfile(their_plugin=UVLOOP_HOOK.format(options=""))
        pytester.syspathinsert()
        args += ["-p", "their_plugin"]
    else:
        pytester.makeconftest(UVLOOP_HOOK.format(options="trylast=True"))
    result = pytester.runpytest(*args)
    result.assert_outcomes(passed=6)  # test_both_by_name runs twice: virtual_clock and uvloop
    out = result.stdout.str()
    assert "PLAIN_LOOP uvloop" in out  # their factory, untouched (they return only uvloop)
    assert "BOTH asyncdonkey" in out and "BOTH uvloop" in out
    assert "SKIPPED" not in out


@pytest.mark.realtime
def test_without_other_hooks_plain_tests_run_on_the_default_loop(pytester):
    _project(pytester, OTHER_TESTS.replace("{other}", "asyncio"))
    result = pytester.runpytest("-s", "-v")
    result.assert_outcomes(passed=5)
    out = result.stdout.str()
    assert "PLAIN_LOOP asyncio" in out  # the event loop policy's loop, as pytest-asyncio makes without hooks
    assert "BOTH asyncdonkey" in out and "BOTH asyncio" in out
    # naming a factory nobody provides fails as it does with pytest-asyncio alone, it is not silently skipped
    pytester.makepyfile(test_uv=PREAMBLE + UVLOOP_TEST)
    result = pytester.runpytest("test_uv.py")
    result.stdout.fnmatch_lines(["*loop_factories*['uvloop']*needs a pytest_asyncio_loop_factories hook*"])
    assert result.ret != 0
    assert "skipped" not in result.stdout.str()


def test_virtual_clock_marker_contradicting_loop_factories_is_a_usage_error(pytester):
    pytester.makeini("[pytest]\nasyncio_default_fixture_loop_scope = function\n")
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.asyncio(loop_factories=["asyncio"])
        @pytest.mark.virtual_clock
        async def test_x():
            pass
        """
    )
    result = pytester.runpytest()
    result.stdout.fnmatch_lines(["*marked virtual_clock, but*loop_factories*do not name 'virtual_clock'*"])
    assert result.ret != 0
