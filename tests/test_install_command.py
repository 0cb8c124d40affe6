"""The missing-extra hint names the install command that fits how this copy of asyncdonkey was installed.

asyncdonkey is not on PyPI, so ``pip install 'asyncdonkey[x]'`` fails for most users: the hint is built from the
distribution's ``direct_url.json`` (PEP 610) and the running interpreter. Each form pip records is built here as
data and given to :func:`install_command_for`; the shell words are checked with ``shlex.split``, as the shell
would read them.
"""

from __future__ import annotations

import importlib.metadata
import json
import shlex
import sys
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from asyncdonkey import extras
from asyncdonkey.extras import install_command, install_command_for, installed_from

PY = "/home/pi/env/bin/python"
ROOT = Path(__file__).resolve().parents[1]


def words(command: str) -> list[str]:
    return shlex.split(command)


def test_an_editable_checkout_gets_pip_install_e_of_the_checkout():
    record = {"url": "file:///home/pi/asyncdonkey", "dir_info": {"editable": True}}
    command = install_command_for("mcap", record, PY)
    assert command == f"{PY} -m pip install -e '/home/pi/asyncdonkey[mcap]'"
    assert words(command) == [PY, "-m", "pip", "install", "-e", "/home/pi/asyncdonkey[mcap]"]


def test_a_directory_installed_without_e_gets_the_directory_without_e():
    record = {"url": "file:///srv/src/asyncdonkey", "dir_info": {}}
    assert words(install_command_for("zenoh", record, PY)) == [
        PY,
        "-m",
        "pip",
        "install",
        "/srv/src/asyncdonkey[zenoh]",
    ]


def test_a_wheel_file_gets_the_same_wheel_with_the_extra():
    wheel = "/home/pi/dist/asyncdonkey-0.1.0-py3-none-any.whl"
    record = {"url": f"file://{wheel}", "archive_info": {"hashes": {"sha256": "0" * 64}}}
    command = install_command_for("tflite", record, PY)
    assert words(command) == [PY, "-m", "pip", "install", f"{wheel}[tflite]"]


def test_a_path_with_spaces_and_escapes_is_one_shell_word():
    record = {"url": "file:///home/pi/my%20cars/asyncdonkey", "dir_info": {"editable": True}}
    assert words(install_command_for("mcap", record, "/opt/my env/bin/python")) == [
        "/opt/my env/bin/python",
        "-m",
        "pip",
        "install",
        "-e",
        "/home/pi/my cars/asyncdonkey[mcap]",
    ]


def test_a_git_url_gets_the_repository_and_the_revision_asked_for():
    record = {
        "url": "https://github.com/asyncdonkey/asyncdonkey",
        "vcs_info": {"vcs": "git", "requested_revision": "main", "commit_id": "1cfff82" + "0" * 33},
    }
    command = install_command_for("mcap", record, PY)
    assert command == f"{PY} -m pip install 'asyncdonkey[mcap] @ git+https://github.com/asyncdonkey/asyncdonkey@main'"


def test_a_git_url_without_a_revision_and_in_a_subdirectory():
    record = {
        "url": "ssh://git@example.org/cars/robots.git",
        "vcs_info": {"vcs": "git", "commit_id": "a" * 40},
        "subdirectory": "asyncdonkey",
    }
    assert words(install_command_for("zenoh", record, PY))[-1] == (
        "asyncdonkey[zenoh] @ git+ssh://git@example.org/cars/robots.git#subdirectory=asyncdonkey"
    )


def test_an_archive_from_a_web_server_gets_a_direct_reference():
    url = "https://cars.example.org/wheels/asyncdonkey-0.1.0-py3-none-any.whl"
    record = {"url": url, "archive_info": {}}
    assert words(install_command_for("mcap", record, PY))[-1] == f"asyncdonkey[mcap] @ {url}"


def test_a_package_index_install_gets_the_name_with_the_extra():
    assert install_command_for("quantize", None, PY) == f"{PY} -m pip install 'asyncdonkey[quantize]'"


def test_this_copy_is_the_editable_checkout_the_tests_run_in():
    """make test installs the checkout with pip install -e: the hint installs into this venv, from this checkout."""
    record = installed_from()
    assert record is not None and record["dir_info"] == {"editable": True}
    assert Path(extras._local_path(record["url"]) or "").resolve() == ROOT
    assert words(install_command("mcap")) == [sys.executable, "-m", "pip", "install", "-e", f"{ROOT}[mcap]"]


def test_an_unreadable_record_counts_as_an_index_install(monkeypatch):
    """A broken direct_url.json must not turn a missing extra into a traceback: the plain name is the fallback."""

    class Dist:
        def __init__(self, text: str | None) -> None:
            self.text = text

        def read_text(self, name: str) -> str | None:
            assert name == "direct_url.json"
            return self.text

    for text in ("{not json", json.dumps(["a list"]), json.dumps({"no": "url"}), None):
        monkeypatch.setattr(importlib.metadata, "distribution", lambda name, text=text: Dist(text))
        assert installed_from() is None
        assert install_command("mcap").endswith(" -m pip install 'asyncdonkey[mcap]'")


def test_a_copy_run_from_its_source_tree_reads_as_an_editable_checkout(monkeypatch):
    """PYTHONPATH=src without installing: no distribution, so the hint names the checkout the module sits in."""

    def missing(name: str) -> object:
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "distribution", missing)
    assert words(install_command("zenoh"))[-2:] == ["-e", f"{ROOT}[zenoh]"]


PATH_CHARS = st.characters(codec="utf-8", exclude_characters="\x00/%", exclude_categories=("Cs", "Cc"))


@given(
    parts=st.lists(st.text(PATH_CHARS, min_size=1, max_size=12), min_size=1, max_size=4),
    extra=st.sampled_from(["mcap", "tflite", "quantize", "zenoh", "donkeycar-cli"]),
    editable=st.booleans(),
)
def test_any_checkout_path_comes_back_as_one_shell_word(parts, extra, editable):
    """Whatever the path (quotes, spaces, $, ;), the shell reads back exactly the path with the extra."""
    path = Path("/", *parts)
    record = {"url": path.as_uri(), "dir_info": {"editable": editable}}
    got = words(install_command_for(extra, record, PY))
    assert got == [PY, "-m", "pip", "install", *(["-e"] if editable else []), f"{path}[{extra}]"]
