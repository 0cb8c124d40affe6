"""asyncdonkey installs and runs outside the checkout: the wheel and sdist that ``make dist`` builds, and the Makefile.

The wheel test builds both archives with the standard frontend (``python -m build``, as ``make dist`` does; the
wheel is built from the sdist, so the sdist is proven complete), installs the wheel into a fresh venv and runs
it there: the console script, ``python -m asyncdonkey.commands``, the modules each extra enables, the
missing-extra hint (which must name the wheel, not the checkout) and the simulated car for 3 s.

To stay quick the new venv gets no dependencies of its own: the wheel goes in with ``--no-deps`` and a ``.pth``
file puts the test venv's site-packages after the new venv's, so numpy, onnxruntime and the extras' packages come
from there while asyncdonkey itself can only come from the wheel (a ``.pth`` line adds a directory to
``sys.path`` without running the ``.pth`` files in it, so the checkout's editable install stays out).
``venv --system-site-packages`` would not do: made from a venv's interpreter it sees the base Python's
site-packages, not the venv's.

The Makefile tests run ``make -n`` (nothing is built): which venv a PYTHON gets, and ``make help``.
"""

from __future__ import annotations

import glob
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import venv
import zipfile
from pathlib import Path

import pytest

import asyncdonkey

ROOT = Path(__file__).resolve().parents[1]
VERSION = asyncdonkey.__version__
WHEEL_NAME = f"asyncdonkey-{VERSION}-py3-none-any.whl"
SDIST_NAME = f"asyncdonkey-{VERSION}.tar.gz"

#: What each extra enables, imported in the installed copy: our modules and the extra's own packages.
EXTRA_IMPORTS = {
    "mcap": ["asyncdonkey.parts.mcap.recorder", "asyncdonkey.parts.mcap.reader", "mcap", "foxglove"],
    "tflite": ["asyncdonkey.parts.tflite_pilot", "ai_edge_litert.interpreter"],
    "quantize": ["asyncdonkey.commands.quantize", "onnx"],
    "zenoh": ["asyncdonkey.parts.zenoh", "asyncdonkey.parts.zenoh.pairing", "zenoh", "cryptography"],
    "donkeycar": ["asyncdonkey.commands.donkey", "PIL", "docopt", "tornado"],
}


def run(*args: object, timeout: float = 120, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(
        [str(a) for a in args], capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env, check=False
    )


def ok(proc: subprocess.CompletedProcess[str]) -> str:
    assert proc.returncode == 0, f"{proc.args}: exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


@pytest.fixture(scope="module")
def dist(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sdist and the wheel built from it, as make dist builds them (into a temporary dist/)."""
    out = tmp_path_factory.mktemp("dist")
    ok(run(sys.executable, "-m", "build", "--outdir", out, ROOT, timeout=300))
    return out


@pytest.fixture(scope="module")
def installed(dist: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh venv with the wheel installed (no deps: they come from the test venv's site-packages, after it)."""
    env_dir = tmp_path_factory.mktemp("wheel-venv") / "venv"
    venv.EnvBuilder(with_pip=False, symlinks=True).create(env_dir)
    python = env_dir / "bin" / "python"
    site = Path(ok(run(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])")).strip())
    (site / "test-venv-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    pip = (sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", "--no-index")
    ok(run(*pip, dist / WHEEL_NAME, timeout=180))
    return env_dir


@pytest.mark.subprocess
def test_the_wheel_holds_the_package_data(dist):
    names = set(zipfile.ZipFile(dist / WHEEL_NAME).namelist())
    for wanted in (
        "asyncdonkey/py.typed",
        "asyncdonkey/parts/mcap/layout.json",
        "asyncdonkey/parts/web/static/drive.html",
        "asyncdonkey/parts/web/static/drive.js",
        "asyncdonkey/parts/web/static/drive.css",
        "asyncdonkey/parts/web/static/calibrate.html",
    ):
        assert wanted in names, wanted
    assert not any(n.startswith(("tests/", "examples/", "docs/")) for n in names)  # the package only
    metadata = zipfile.ZipFile(dist / WHEEL_NAME).read(f"asyncdonkey-{VERSION}.dist-info/METADATA").decode()
    assert f"\nVersion: {VERSION}\n" in metadata
    assert "Project-URL: Source, https://github.com/asyncdonkey/asyncdonkey" in metadata
    assert "Provides-Extra: mcap" in metadata and "Provides-Extra: zenoh" in metadata


@pytest.mark.subprocess
def test_the_sdist_is_the_whole_source(dist):
    """The sdist builds the wheel (the fixture did) and holds what make test and make run need."""
    with tarfile.open(dist / SDIST_NAME) as sdist:
        names = set(sdist.getnames())
    top = f"asyncdonkey-{VERSION}"
    for wanted in ("Makefile", "CHANGELOG.md", "tests/conftest.py", "docs/install.md", "examples/car.py", ".ci/run"):
        assert f"{top}/{wanted}" in names, wanted
    assert f"{top}/examples/models/sim_pilot.onnx" in names
    assert not any("__pycache__" in n for n in names)


@pytest.mark.subprocess
def test_the_installed_wheel_runs_from_its_own_venv(installed, dist, tmp_path):
    python, bin_dir = installed / "bin" / "python", installed / "bin"
    where = Path(ok(run(python, "-c", "import asyncdonkey; print(asyncdonkey.__file__)", cwd=tmp_path)).strip())
    assert where.is_relative_to(installed) and not where.is_relative_to(ROOT), where
    assert ok(run(bin_dir / "asyncdonkey", "--version", cwd=tmp_path)).strip().endswith(VERSION)
    assert "run" in ok(run(bin_dir / "asyncdonkey", "--help", cwd=tmp_path))
    assert "run" in ok(run(python, "-m", "asyncdonkey.commands", "--help", cwd=tmp_path))
    # the package data is found where the code looks for it
    ok(
        run(
            python,
            "-c",
            "from asyncdonkey.parts.mcap.layout import layout_path; import json; json.loads(layout_path().read_text());"
            "from asyncdonkey.parts.web.controller import _load_static; assert 'drive.html' in _load_static()",
            cwd=tmp_path,
        )
    )


@pytest.mark.subprocess
@pytest.mark.parametrize("extra", sorted(EXTRA_IMPORTS))
def test_each_extras_modules_import_in_the_installed_copy(installed, tmp_path, extra):
    code = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module(m)\n"
    ok(run(installed / "bin" / "python", "-c", code, *EXTRA_IMPORTS[extra], cwd=tmp_path))


@pytest.mark.subprocess
def test_the_missing_extra_hint_names_the_wheel_it_came_from(installed, dist, tmp_path):
    python = installed / "bin" / "python"
    hint = ok(run(python, "-c", "from asyncdonkey.extras import install_command; print(install_command('mcap'))"))
    assert hint.strip() == f"{python} -m pip install '{dist / WHEEL_NAME}[mcap]'"


@pytest.mark.subprocess
def test_the_installed_wheel_drives_the_simulated_car(installed, tmp_path):
    """From another directory, as a user outside the checkout runs it: exit 0 and the drive's report."""
    proc = run(installed / "bin" / "asyncdonkey", "run", ROOT / "examples" / "car.py", "--duration", "3", cwd=tmp_path)
    ok(proc)
    report = proc.stderr  # the report goes to stderr, as a drive's log does
    assert re.search(r"^loops: [1-9]\d* in ", report, flags=re.MULTILINE), report[-2000:]
    assert "stopped by: time limit reached (duration)" in report, report[-2000:]


# ---------------------------------------------------------------------------------------------------- Makefile
def python_version_of(interpreter: str) -> str | None:
    """``3.13`` for a Python 3.13 interpreter; None when it does not run."""
    probe = run(interpreter, "-c", "import sys; print('%d.%d' % sys.version_info[:2])", timeout=30)
    return probe.stdout.strip() if probe.returncode == 0 else None


def other_python(unlike: str | None = None) -> str | None:
    """An interpreter (on PATH or installed by pyenv) of another minor version than ``unlike``.

    ``unlike`` defaults to this interpreter's version. The Makefile's own default is ``python3``, which need not be
    the interpreter running the suite: CI runs it again on 3.13 while ``python3`` is 3.11.
    """
    unlike = unlike or f"{sys.version_info[0]}.{sys.version_info[1]}"
    pyenv_root = os.environ.get("PYENV_ROOT", str(Path.home() / ".pyenv"))
    for minor in ("3.11", "3.12", "3.13", "3.14"):
        if minor == unlike:
            continue
        found = shutil.which(f"python{minor}")
        candidates = [found] if found else []
        candidates += sorted(glob.glob(f"{pyenv_root}/versions/{minor}.*/bin/python{minor}"))
        for candidate in candidates:
            if python_version_of(candidate) == minor:
                return candidate
    return None


def make(*args: str) -> subprocess.CompletedProcess[str]:
    """``make`` as a user at a shell runs it: not as a sub-make of the ``make test`` running this suite.

    The outer make hands its command-line variables down through MAKEFLAGS (CI runs ``make test PYTHON=…
    VENV=.venv313``), and a sub-make takes them over its own command line; without this the test would check
    the outer call's VENV, not what the PYTHON given here picks.
    """
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "VIRTUAL_ENV", "MAKEFLAGS", "MFLAGS", "MAKELEVEL", "MAKEOVERRIDES", "VENV", "PYTHON")
    }
    return subprocess.run(
        ["make", "--no-print-directory", "-C", str(ROOT), *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        check=False,
    )


needs_make = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


@pytest.mark.subprocess
@needs_make
def test_another_python_gets_a_venv_of_its_own():
    """A PYTHON of another version than make's default (``python3``) gets .venv<major><minor>, never .venv."""
    default = python_version_of("python3")
    other = other_python(unlike=default)
    if other is None:
        pytest.skip("no interpreter of another Python version than python3's here")
    version = (python_version_of(other) or "").replace(".", "")
    out = ok(make("-n", "test-fast", f"PYTHON={other}"))
    assert f".venv{version}/bin/python -m pytest" in out, out
    assert ".venv/" not in out, out


@pytest.mark.subprocess
@needs_make
def test_a_venv_made_by_another_python_is_refused_with_the_fix():
    """make test PYTHON=python3.13 VENV=<a 3.11 venv> must not run the tests on 3.11."""
    other = other_python()
    if other is None:
        pytest.skip("no interpreter of another Python version here")
    proc = make("-n", "test-fast", f"PYTHON={other}", f"VENV={sys.prefix}")
    assert proc.returncode != 0 and "pytest" not in proc.stdout, proc.stdout
    mine = f"{sys.version_info[0]}.{sys.version_info[1]}"
    assert f"{sys.prefix} was made by Python {mine}, but PYTHON={other} is Python " in proc.stderr, proc.stderr
    assert "leave VENV unset" in proc.stderr and f"make clean VENV={sys.prefix}" in proc.stderr


@pytest.mark.subprocess
@needs_make
def test_a_python_that_does_not_run_is_named():
    proc = make("-n", "test-fast", "PYTHON=/nonexistent/python3")
    assert proc.returncode != 0 and "PYTHON=/nonexistent/python3 does not run" in proc.stderr, proc.stderr


@pytest.mark.subprocess
@needs_make
def test_bare_make_lists_every_target_with_one_line():
    listed = dict(re.findall(r"^  (\S+) +(\S.*)$", ok(make()), flags=re.MULTILINE))  # bare make is make help
    assert ok(make("help")) == ok(make())
    phony = set()
    for line in (ROOT / "Makefile").read_text().splitlines():
        if line.startswith(".PHONY:"):
            phony.update(line.split(":", 1)[1].split())
    assert {"help", "run", "test", "test-fast", "dist", "clean"} <= phony
    assert phony <= set(listed), phony - set(listed)  # every target has its line


def test_the_docs_name_the_wheel_of_this_version():
    """Every wheel file the README, the docs and the changelog name is the one make dist builds now."""
    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]
    named = {
        (page.name, m)
        for page in pages
        for m in re.findall(r"asyncdonkey-([0-9][^-\s]*)-py3-none-any\.whl", page.read_text(encoding="utf-8"))
    }
    assert named, "no page names the wheel"
    assert {version for _, version in named} == {VERSION}, sorted(named)
