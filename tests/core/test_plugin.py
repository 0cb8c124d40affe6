"""The pytest plugin: the virtual clock (by marker, fixture or factory name) and checked mode (by ini option or
marker), each only for the projects and tests that ask; everything else untouched."""

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
    # naming a factory nobody provides fails as it does with pytest-asyncio alone, it is not silently skipped:
    # beside tests that asked for the virtual clock, with our message; alone, pytest-asyncio's own (no hook then)
    pytester.makepyfile(test_uv=PREAMBLE + UVLOOP_TEST)
    result = pytester.runpytest()
    result.stdout.fnmatch_lines(["*loop_factories*['uvloop']*needs a pytest_asyncio_loop_factories hook*"])
    assert result.ret != 0 and "skipped" not in result.stdout.str()
    result = pytester.runpytest("test_uv.py")
    result.stdout.fnmatch_lines(["*loop_factories*requires at least one pytest_asyncio_loop_factories hook*"])
    assert result.ret != 0 and "skipped" not in result.stdout.str()


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


# ------------------------------------------------- a project that does not use the virtual clock: as without us
NOT_OURS_INI = """
    [pytest]
    asyncio_default_fixture_loop_scope = function
    asyncio_default_test_loop_scope = session
"""
NOT_OURS_A = """
    import asyncio
    import pytest

    def test_a1():
        pass

    @pytest.mark.asyncio
    async def test_a2():
        pytest.loop_a2 = asyncio.get_running_loop()
        print("LOOP", type(pytest.loop_a2).__qualname__)

    @pytest.mark.asyncio
    async def test_a3(virtual_clock):
        assert virtual_clock == "their own fixture"
        print("LOOP", type(asyncio.get_running_loop()).__qualname__)

    def test_a4():
        pass
"""
NOT_OURS_B = """
    import asyncio
    import pytest

    def test_b1():
        pass

    @pytest.mark.asyncio
    async def test_b2():
        print("SAME_LOOP_AS_A2", asyncio.get_running_loop() is pytest.loop_a2)
"""
NOT_OURS_CONFTEST = """
    import pytest

    @pytest.fixture
    def virtual_clock():
        return "their own fixture"
"""


@pytest.mark.realtime
def test_a_project_that_never_asks_for_the_virtual_clock_runs_as_with_pytest_asyncio_alone(pytester):
    """Its tests keep their order, ids and loops (pytest-asyncio's default, one loop for the session), and its own
    fixture named ``virtual_clock`` stays its own. The plugin's hook, once registered, made pytest-asyncio
    parametrize every asyncio test: a session-scoped loop then pulled test_b2 ahead of test_a3."""
    pytester.makeini(NOT_OURS_INI)
    pytester.makeconftest(NOT_OURS_CONFTEST)
    pytester.makepyfile(test_a=NOT_OURS_A, test_b=NOT_OURS_B)

    def run(*args: str) -> list[str]:
        result = pytester.runpytest("-v", "-s", "-p", "no:cacheprovider", *args)
        result.assert_outcomes(passed=6)
        return [line for line in result.outlines if line.startswith("test_")]

    alone = run("-p", "no:asyncdonkey")
    assert run() == alone
    assert alone == [
        "test_a.py::test_a1 PASSED",
        "test_a.py::test_a2 LOOP _UnixSelectorEventLoop",
        "test_a.py::test_a3 LOOP _UnixSelectorEventLoop",
        "test_a.py::test_a4 PASSED",
        "test_b.py::test_b1 PASSED",
        "test_b.py::test_b2 SAME_LOOP_AS_A2 True",
    ]


# -------------------------------------------------------------------------------------- checked mode: opt-in
CAMERA_PROJECT = """
    import numpy as np
    import pytest
    from asyncdonkey import Vehicle

    class FakeCamera:
        \"\"\"A project's stand-in camera: float64 zeros, or a tuple, where the car's camera gives uint8.\"\"\"

        def __init__(self, frame):
            self.frame = frame

        def run(self):
            return self.frame

    FRAMES = {"float64": np.zeros((120, 160, 3)), "tuple": (0, 0, 0)}

    async def drive(kind):
        v = Vehicle()
        v.add(FakeCamera(FRAMES[kind]), outputs=["cam/image_array"], name="camera")
        report = await v.run(20, 3)
        assert report.loops == 3 and report.part_errors == {}
        return report

    @pytest.mark.asyncio
    @pytest.mark.virtual_clock
    @pytest.mark.asyncdonkey_checked
    async def test_marked_checked():
        await drive("float64")  # (runs first: the tests after it are not checked)

    @pytest.mark.asyncio
    @pytest.mark.virtual_clock
    @pytest.mark.parametrize("kind", sorted(FRAMES))
    async def test_fake_camera(kind):
        assert not (await drive(kind)).checked

    @pytest.mark.asyncio
    @pytest.mark.virtual_clock
    @pytest.mark.asyncdonkey_checked(False)
    async def test_marked_unchecked():
        assert not (await drive("tuple")).checked
"""
PLAIN_INI = "[pytest]\nasyncio_default_fixture_loop_scope = function\n"
VIOLATION = "*ContractViolation: part 'camera' wrote channel 'cam/image_array': got *"


def _failed(result: pytest.RunResult) -> list[str]:
    """The ids of the failed tests, from the run's ``-rf`` summary."""
    return [line.split(" ")[1] for line in result.outlines if line.startswith("FAILED ")]


@pytest.mark.subprocess
def test_checked_mode_is_off_unless_the_project_or_the_test_asks(pytester):
    """A separate project (its own pytest process) whose fake camera breaks cam/image_array's contract: its tests
    pass, as its car drives; the marker checks that one test, naming the channel."""
    pytester.makeini(PLAIN_INI)
    pytester.makepyfile(test_camera=CAMERA_PROJECT)
    result = pytester.runpytest_subprocess("-rf", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=3, failed=1)
    assert _failed(result) == ["test_camera.py::test_marked_checked"]
    result.stdout.fnmatch_lines([VIOLATION + "float64*"])


@pytest.mark.asyncdonkey_checked(False)  # the default of a session that did not opt in, for the one run in-process
def test_the_ini_option_turns_checked_mode_on_for_the_project(pytester):
    from asyncdonkey import Vehicle

    before = Vehicle.checked_by_default
    pytester.makeini(PLAIN_INI + "asyncdonkey_checked = true\n")
    pytester.makepyfile(test_camera=CAMERA_PROJECT)
    result = pytester.runpytest("-rf", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=1, failed=3)  # only the test marked asyncdonkey_checked(False) drives
    assert _failed(result) == [
        "test_camera.py::test_marked_checked",
        "test_camera.py::test_fake_camera[float64]",
        "test_camera.py::test_fake_camera[tuple]",
    ]
    for got in ("an array of dtype float64", "tuple of 3 items, not an array"):
        result.stdout.fnmatch_lines([f"{VIOLATION}{got}*"])
    assert Vehicle.checked_by_default is before  # put back when the session ended


def test_a_marker_argument_that_is_not_a_bool_is_a_usage_error(pytester):
    pytester.makeini(PLAIN_INI)
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.asyncdonkey_checked("yes")
        def test_x():
            pass
        """
    )
    result = pytester.runpytest("-p", "no:cacheprovider")
    result.stderr.fnmatch_lines(["*test_x: asyncdonkey_checked(on) takes True or False, got 'yes'*"])
    assert result.ret != 0
