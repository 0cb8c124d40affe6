"""The suite's own guard: a ``subprocess`` test that leaves a process running fails, and the process is killed.

Run on a copy of the suite's conftest.py in a pytest of its own, so the failing test fails there, not here.
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

CONFTEST = Path(__file__).resolve().parents[1] / "conftest.py"


def running(pid: int) -> bool:
    """Whether ``pid`` is still running (a zombie has ended: only its exit status is left)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return False
    return stat[stat.rfind(b")") + 2 :].split()[0] not in (b"Z", b"X")


@pytest.mark.subprocess
def test_a_process_left_running_fails_its_test_by_name_and_is_killed(pytester: pytest.Pytester) -> None:
    pidfile = pytester.path / "pid"
    pytester.makeconftest(CONFTEST.read_text())
    pytester.makeini("[pytest]\nmarkers =\n    subprocess: starts a process\n")
    pytester.makepyfile(
        f"""
        import subprocess
        import sys
        from pathlib import Path

        import pytest


        @pytest.mark.subprocess
        def test_leaves_a_car_running():
            proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)  # the stuck car"])
            Path({str(pidfile)!r}).write_text(str(proc.pid))


        @pytest.mark.subprocess
        def test_waits_for_its_process():
            subprocess.run([sys.executable, "-c", "pass"], check=True, timeout=60)
        """
    )
    result = pytester.runpytest_subprocess("-p", "no:randomly", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=2, errors=1)
    result.stdout.fnmatch_lines(
        ["*test_leaves_a_car_running left 1 process(es) running 2 s after it ended (killed now): *time.sleep(120)*"]
    )
    assert not running(int(pidfile.read_text()))
    assert "test_waits_for_its_process left" not in result.stdout.str()


@pytest.mark.subprocess
def test_what_a_wider_fixtures_process_starts_during_a_test_is_that_fixtures(pytester: pytest.Pytester) -> None:
    """A module's browser starts helpers when a page first needs them and keeps them: not the test's leftovers."""
    pidfile = pytester.path / "helper-child"
    pytester.makeconftest(CONFTEST.read_text())
    pytester.makeini("[pytest]\nmarkers =\n    subprocess: starts a process\n")
    helper = (
        "import subprocess, sys\n"
        "sys.stdin.readline()\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'])\n"
        f"open({str(pidfile)!r}, 'w').write(str(child.pid))\n"
        "print('started', flush=True)\n"
        "sys.stdin.readline()\n"
        "child.kill(); child.wait()\n"
    )
    pytester.makepyfile(
        f"""
        import subprocess
        import sys

        import pytest


        @pytest.fixture(scope="module")
        def browser_like():
            proc = subprocess.Popen(
                [sys.executable, "-c", {helper!r}], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
            )
            yield proc
            proc.stdin.write("end\\n")
            proc.stdin.close()
            proc.wait(timeout=30)


        @pytest.mark.subprocess
        def test_asks_the_module_process_for_a_helper(browser_like):
            browser_like.stdin.write("start a helper\\n")
            browser_like.stdin.flush()
            assert browser_like.stdout.readline() == "started\\n"  # the helper runs under the module's process


        @pytest.mark.subprocess
        def test_leaves_its_own_process(browser_like):
            subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)  # the test's own"])
        """
    )
    result = pytester.runpytest_subprocess("-p", "no:randomly", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=2, errors=1)
    assert "test_asks_the_module_process_for_a_helper left" not in result.stdout.str()
    result.stdout.fnmatch_lines(["*test_leaves_its_own_process left 1 process(es)*the test's own*"])
    assert not running(int(pidfile.read_text()))  # the module's fixture ended its helper itself
