"""Shared test set-up. The virtual clock comes from asyncdonkey's own pytest plugin (entry point).

**The kinds guard.** Every test that needs something beyond the deterministic core carries a marker saying what
(``pyproject.toml`` registers them, ``docs/testing.md`` tells them apart): ``realtime``, ``browser``,
``donkeycar``, ``network``, ``subprocess``. ``-m "not realtime and not browser and not donkeycar and not network
and not subprocess"`` (``make test-fast``) is then the part of the suite that is deterministic and fast, and it
stays so only if a new test cannot forget its marker. So while each test runs (set-up and teardown included) this
module watches for what each kind does, and a test that did it without the marker fails at its teardown, saying
what it saw:

* ``realtime``: an event loop other than the virtual clock ran (``asyncio.run``, ``run_blocking``, an
  ``asyncio.Runner``, a real pytest-asyncio loop, uvloop). Seen where asyncio marks the running loop
  (``asyncio.events._set_running_loop``, wrapped here before uvloop is imported, which keeps a reference to it);
* ``network``: a socket bound or connected on IPv4 or IPv6 (the ``socket.bind`` and ``socket.connect`` audit
  events: aiohttp, websockets, raw sockets; a Unix socket in a temporary directory is not the network), or a Zenoh
  session opened (``zenoh.open``: Zenoh's sockets are its own native code's);
* ``subprocess``: a process started (the ``subprocess.Popen``, ``os.posix_spawn``, ``os.fork``, ``os.exec``,
  ``os.system`` and ``os.spawn`` audit events);
* ``donkeycar``: the test function, one of its fixtures or a helper it calls (a function or class of the test
  package, followed by name) imports Donkeycar or names one of its modules, classes or functions; or the test is
  one of Donkeycar's own.

What happens in threads that were running before the test started is not the test's (a thread left behind by an
earlier test). The guard cannot see everything a kind covers: a wait on ``time.sleep`` for a thread, an assertion
on wall-clock time or a helper reached only through an object are the author's to mark (see docs/testing.md).

**No process outlives its test.** After each ``subprocess`` test, a process it started (a child of this one, or
one of that child's) that is still running a moment later is killed, and the test fails naming its command line:
a car that hangs instead of exiting must fail the test that started it, not run on for hours after it.
"""

from __future__ import annotations

import asyncio
import asyncio.events
import dis
import os
import signal
import socket
import sys
import threading
import time
import types
from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings

from asyncdonkey.clock.virtual_loop import VirtualClockLoop

# Property tests assert behaviour, not speed: hypothesis's default 200 ms deadline per example turns a loaded CI
# machine's pause into a failure (DeadlineExceeded, or Flaky when the replay is fast). Timing lives in benchmarks/.
settings.register_profile("asyncdonkey", deadline=None)
settings.load_profile("asyncdonkey")

KINDS = ("realtime", "browser", "donkeycar", "network", "subprocess")
TESTS = Path(__file__).resolve().parent

_INET = (socket.AF_INET, socket.AF_INET6)
_SOCKET_EVENTS = frozenset({"socket.bind", "socket.connect"})
_PROCESS_EVENTS = frozenset(
    {"subprocess.Popen", "os.posix_spawn", "os.fork", "os.forkpty", "os.exec", "os.system", "os.spawn"}
)
_WATCHED = _SOCKET_EVENTS | _PROCESS_EVENTS


class _Watch:
    """What the running test did, by kind (the first thing seen of each), and the threads that are not its own."""

    item: pytest.Item | None = None
    seen: dict[str, str] = {}
    foreign_threads: frozenset[int] = frozenset()

    @classmethod
    def saw(cls, kind: str, what: str) -> None:
        if cls.item is not None and threading.get_ident() not in cls.foreign_threads:
            cls.seen.setdefault(kind, what)


def _audit(event: str, args: tuple[Any, ...]) -> None:
    if event not in _WATCHED or _Watch.item is None:
        return
    try:  # (an exception here would be raised by the call that was audited)
        if event in _SOCKET_EVENTS:
            if getattr(args[0], "family", None) in _INET:
                _Watch.saw("network", f"{event} {args[1]!r}")
        else:
            _Watch.saw("subprocess", f"{event} {args[0]!r}"[:200] if args else event)
    except Exception:  # pragma: no cover - the guard must never break the code it watches
        pass


sys.addaudithook(_audit)  # (an audit hook cannot be removed: it does nothing outside a test)

# ctypes finds the C library by running ldconfig once, the first time asyncdonkey asks for it in each errno mode:
# a cache filled by whichever test comes first, not a process that test starts. Filled here, before any test.
from asyncdonkey.clock import _libc  # noqa: E402

_libc._library(True)
_libc._library(False)


def _watching_running_loop(set_running_loop: Callable[[Any], None]) -> Callable[[Any], None]:
    def _set_running_loop(loop: Any) -> None:
        if loop is not None and _Watch.item is not None and not isinstance(loop, VirtualClockLoop):
            _Watch.saw("realtime", f"a real event loop ran: {type(loop).__module__}.{type(loop).__qualname__}")
        set_running_loop(loop)

    return _set_running_loop


if "uvloop" in sys.modules:  # pragma: no cover - nothing imports it before this module
    raise RuntimeError("tests/conftest.py must wrap asyncio._set_running_loop before uvloop is imported")
asyncio.events._set_running_loop = asyncio._set_running_loop = _watching_running_loop(  # type: ignore[attr-defined]
    asyncio.events._set_running_loop  # type: ignore[attr-defined]
)

try:
    import zenoh
except ImportError:  # pragma: no cover - the zenoh extra is part of make test
    zenoh = None
if zenoh is not None:
    _zenoh_open = zenoh.open

    def _watched_zenoh_open(*args: Any, **kwargs: Any) -> Any:
        _Watch.saw("network", "zenoh.open")
        return _zenoh_open(*args, **kwargs)

    zenoh.open = _watched_zenoh_open


# ------------------------------------------------------------------------------------------------- donkeycar
def _donkeycar_name(name: object) -> bool:
    return isinstance(name, str) and (name == "donkeycar" or name.startswith("donkeycar."))


def _is_donkeycars(obj: Any) -> bool:
    """A module, class or function of Donkeycar's."""
    if isinstance(obj, types.ModuleType):
        return _donkeycar_name(obj.__name__)
    return _donkeycar_name(getattr(obj, "__module__", None))


def _ours(obj: Any) -> bool:
    """A function or class of the test package (followed when looking for Donkeycar)."""
    code = getattr(obj, "__code__", None)
    if isinstance(obj, type):
        module = sys.modules.get(obj.__module__)
        filename = getattr(module, "__file__", None)
    else:
        filename = code.co_filename if code is not None else None
    return filename is not None and Path(filename).is_relative_to(TESTS)


_donkeycar_cache: dict[Any, str | None] = {}


def _donkeycar_in(obj: Any, visiting: set[int]) -> str | None:
    """How ``obj`` (a test function, fixture, helper or class of the test package) uses Donkeycar, or None."""
    key = id(obj)
    if key in visiting:
        return None
    try:
        if obj in _donkeycar_cache:
            return _donkeycar_cache[obj]
    except TypeError:  # unhashable
        pass
    visiting.add(key)
    found: str | None = None
    if isinstance(obj, type):
        for member in vars(obj).values():
            member = getattr(member, "__func__", member)  # staticmethod, classmethod
            if isinstance(member, types.FunctionType) and (found := _donkeycar_in(member, visiting)):
                break
    else:
        inner = getattr(getattr(obj, "hypothesis", None), "inner_test", None)  # a @given test's own body
        func = inner if inner is not None else getattr(obj, "__wrapped__", obj)
        code, namespace = getattr(func, "__code__", None), getattr(func, "__globals__", {})
        codes = [code] if code is not None else []
        while codes and found is None:
            code = codes.pop()
            codes.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
            for ins in dis.get_instructions(code):
                if ins.opname == "IMPORT_NAME" and _donkeycar_name(ins.argval):
                    found = f"{func.__qualname__} imports {ins.argval}"
                elif ins.opname in ("LOAD_GLOBAL", "LOAD_NAME") and ins.argval in namespace:
                    value = namespace[ins.argval]
                    if _is_donkeycars(value):
                        found = f"{func.__qualname__} uses {ins.argval} (Donkeycar's)"
                    elif _ours(value) and value is not func:
                        found = _donkeycar_in(value, visiting)
                if found:
                    break
    visiting.discard(key)
    try:
        _donkeycar_cache[obj] = found
    except TypeError:
        pass
    return found


def _donkeycar_evidence(item: pytest.Item) -> str | None:
    function = getattr(item, "function", None)
    if function is None:
        return None
    if _is_donkeycars(function):
        return f"it is Donkeycar's own test ({function.__module__})"
    if found := _donkeycar_in(function, set()):
        return found
    for defs in getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {}).values():
        for fixturedef in defs:
            if _ours(fixturedef.func) and (found := _donkeycar_in(fixturedef.func, set())):
                return f"fixture {fixturedef.argname}: {found}"
    for name, value in getattr(getattr(item, "callspec", None), "params", {}).items():
        if _is_donkeycars(value):
            return f"its parameter {name} is Donkeycar's"
    return None


# ---------------------------------------------------------------------------------------- leftover processes
#: how long a test's processes may take to finish exiting after it (a process killed or told to stop, not waited)
LEFTOVER_GRACE_S = 2.0


def _processes() -> dict[tuple[int, int], tuple[int, bytes]]:
    """Every live process: ``(pid, start time) -> (parent pid, state)``, read from /proc (zombies are ended)."""
    found: dict[tuple[int, int], tuple[int, bytes]] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                stat = f.read()
        except OSError:  # it ended meanwhile
            continue
        fields = stat[stat.rfind(b")") + 2 :].split()  # after the command name, which may hold spaces
        if fields[0] not in (b"Z", b"X"):
            found[(int(name), int(fields[19]))] = (int(fields[1]), fields[0])
    return found


def _descendants(keep_out: frozenset[tuple[int, int]] = frozenset()) -> set[tuple[int, int]]:
    """This process's live children, their children, and so on, as ``(pid, start time)``; the trees under the
    processes in ``keep_out`` are not followed (they are listed themselves, if alive)."""
    procs = _processes()
    ours: set[tuple[int, int]] = set()
    todo = [os.getpid()]
    while todo:
        parent = todo.pop()
        for key, (ppid, _) in procs.items():
            if ppid == parent and key not in ours:
                ours.add(key)
                if key not in keep_out:
                    todo.append(key[0])
    return ours


def _command_line(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip() or f"pid {pid}"
    except OSError:
        return f"pid {pid}"


@pytest.fixture(autouse=True)
def _no_process_outlives_its_test(request: pytest.FixtureRequest) -> Generator[None, None, None]:
    """After a ``subprocess`` test (and its fixtures, which this one outlasts), kill what it left running and fail
    it, naming the command lines.

    Processes of wider-scoped fixtures were already running when it started, and what they start meanwhile is
    theirs to end: a module's browser starts its renderer, storage and GPU helpers when a page first needs them
    and keeps them for its own lifetime, so only trees started by the test itself are held to its end."""
    if request.node.get_closest_marker("subprocess") is None:
        yield
        return
    before = frozenset(_descendants())
    yield
    deadline = time.monotonic() + LEFTOVER_GRACE_S
    while (left := _descendants(keep_out=before) - before) and time.monotonic() < deadline:
        time.sleep(0.02)
    if not left:
        return
    lines = {pid: _command_line(pid) for pid, _ in left}
    for pid, _ in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    pytest.fail(
        f"{request.node.nodeid} left {len(lines)} process(es) running {LEFTOVER_GRACE_S:g} s after it ended "
        "(killed now): " + "; ".join(f"[{pid}] {cmd[:300]}" for pid, cmd in sorted(lines.items())),
        pytrace=False,
    )


# ------------------------------------------------------------------------------------------------------ hooks
@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Generator[None, object, object]:
    _Watch.item, _Watch.seen = item, {}
    main = threading.main_thread().ident
    _Watch.foreign_threads = frozenset(t.ident for t in threading.enumerate() if t.ident != main)
    try:
        return (yield)
    finally:
        _Watch.item = None


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Generator[None, None, None]:
    yield  # (a teardown that failed is reported as it is)
    seen = dict(_Watch.seen)
    if (found := _donkeycar_evidence(item)) is not None:
        seen.setdefault("donkeycar", found)
    marked = {m.name for m in item.iter_markers() if m.name in KINDS}
    missing = {kind: what for kind, what in seen.items() if kind not in marked}
    if missing:
        pytest.fail(
            f"{item.nodeid} is not marked with the kind of test it is: "
            + "; ".join(f"@pytest.mark.{kind} ({what})" for kind, what in sorted(missing.items()))
            + ". See docs/testing.md.",
            pytrace=False,
        )
