"""One owner per device across processes: an advisory ``flock`` on a small file per device.

Why this exists: a chip such as a PCA9685 keeps generating the last pulses it was given, whoever gave them. A
second car started on a chip that another car drives would re-initialise it (its outputs go off with no
warning) and then both would write to it; when the second one exits, the chip shows its last pulses while the
first car believes it writes its own. So the first process to open a device owns it until it exits, and
another process is refused before it sends the chip anything.

Why ``flock``: the kernel drops the lock when the last descriptor of the locked file closes, which includes a
process killed with SIGKILL or crashing in native code. A pid file would stay behind and need guessing
whether its pid is still the owner; a flock can never be stale. The lock file also holds the owner's pid,
command line and start time, only so that the refusal can name it.

Within one process the lock is counted: every user of a device in the process shares it (two descriptors of
one process would conflict with each other under flock). A child forked without ``exec`` would share the
locked descriptor and keep the device locked after its parent died, so the child's copies are closed right
after a fork (``os.register_at_fork``); children started with ``subprocess`` never inherit them (the
descriptors are close-on-exec).

Where: the first writable directory of ``/run/lock`` (a tmpfs, emptied at boot), ``$XDG_RUNTIME_DIR``, then
the temporary directory. The owner removes its file when it lets go; a killed owner leaves an unlocked file
that the next owner reuses.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import AsyncdonkeyError

__all__ = ["LOCK_DIR_CANDIDATES", "DeviceOwner", "LockHeld", "acquire", "held", "lock_dir", "read_owner", "release"]

#: Tried first, in order, before ``$XDG_RUNTIME_DIR`` and the temporary directory.
LOCK_DIR_CANDIDATES: tuple[str, ...] = ("/run/lock",)
#: Reading the owner of a lock that was just taken: how often and how long to wait for its name to appear.
_OWNER_READS = 5
_OWNER_READ_PAUSE_S = 0.01


def lock_dir() -> str:
    """The directory lock files go in: the first writable one of ``/run/lock``, ``$XDG_RUNTIME_DIR``, temp.

    Every process that may open the same device must get the same answer, which holds for the processes of one
    user (and for all users on a Raspberry Pi, whose ``/run/lock`` is writable by everyone).
    """
    for folder in (*LOCK_DIR_CANDIDATES, os.environ.get("XDG_RUNTIME_DIR", "")):
        if folder and os.path.isdir(folder) and os.access(folder, os.W_OK | os.X_OK):
            return folder
    return tempfile.gettempdir()


@dataclass(frozen=True, slots=True)
class DeviceOwner:
    """Who holds a device: what the lock file says."""

    pid: int
    command: str
    started: float  # seconds since the epoch, when the owner process started
    device: str = ""

    def describe(self) -> str:
        """``process 12345 (asyncdonkey run car.py), started 17:02:11`` (the date too if not today)."""
        when = time.localtime(self.started)
        fmt = "%H:%M:%S" if when[:3] == time.localtime()[:3] else "%Y-%m-%d %H:%M:%S"
        return f"process {self.pid} ({self.command}), started {time.strftime(fmt, when)}"


class LockHeld(AsyncdonkeyError):
    """Another process holds the lock at ``path``; ``owner`` is what its file says (``None`` if nothing
    readable names a live process)."""

    def __init__(self, path: str, owner: DeviceOwner | None) -> None:
        super().__init__(path)
        self.path = path
        self.owner = owner


def _command_line() -> str:
    """This process's command line as a user typed it (``asyncdonkey run car.py``, ``python -m pytest``)."""
    orig = list(getattr(sys, "orig_argv", []))
    if "-m" in orig[1:]:
        words = ["python", *orig[orig.index("-m", 1) :]]
    elif sys.argv and sys.argv[0] not in ("", "-c"):
        words = [os.path.basename(sys.argv[0]), *sys.argv[1:]]
    else:
        words = ["python", *orig[1:2]]
    text = " ".join(words)
    return text if len(text) <= 160 else text[:157] + "..."


def _process_start_time() -> float:
    """When this process started (from ``/proc``), or now where ``/proc`` cannot tell."""
    try:
        stat = Path("/proc/self/stat").read_text()
        ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22, starttime, in clock ticks since boot
        with open("/proc/stat") as f:
            btime = next(int(line.split()[1]) for line in f if line.startswith("btime "))
        return btime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return time.time()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


def _parse_owner(text: str) -> DeviceOwner | None:
    try:
        d = json.loads(text)
        return DeviceOwner(int(d["pid"]), str(d["command"]), float(d["started"]), str(d.get("device", "")))
    except (ValueError, TypeError, KeyError):
        return None


def read_owner(path: str) -> DeviceOwner | None:
    """The live owner the lock file at ``path`` names, or ``None``.

    An owner writes its name just after it takes the lock, and a killed owner's name stays in the file until
    the next owner overwrites it, so a name that is missing or names a dead process is read again a few times.
    """
    for attempt in range(_OWNER_READS):
        try:
            owner = _parse_owner(Path(path).read_text())
        except OSError:
            owner = None
        if owner is not None and _alive(owner.pid):
            return owner
        if attempt + 1 < _OWNER_READS:
            time.sleep(_OWNER_READ_PAUSE_S)
    return None


def _open(path: str) -> tuple[int, bool]:
    """Open (creating it if needed) the lock file: ``(fd, writable)``.

    Another user's file in a sticky directory may refuse writing (and ``O_CREAT``, with
    ``fs.protected_regular``); read-only is enough to lock it, only not to write our name into it.
    """
    while True:
        try:
            return os.open(path, os.O_RDWR | os.O_CLOEXEC), True
        except FileNotFoundError:
            pass
        except PermissionError:
            return os.open(path, os.O_RDONLY | os.O_CLOEXEC), False
        try:
            return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644), True
        except FileExistsError:
            continue  # created by another process between the two opens


def _same_file(fd: int, path: str) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _lock(path: str, device: str) -> int:
    """Take the lock at ``path`` for this process and write its name into the file; the locked fd."""
    for _ in range(20):
        fd, writable = _open(path)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise LockHeld(path, read_owner(path)) from None
        except BaseException:
            os.close(fd)
            raise
        if not _same_file(fd, path):
            os.close(fd)  # its last owner removed it between our open and our lock: lock the current file
            continue
        if writable:
            me = {"pid": os.getpid(), "command": _command_line(), "started": _process_start_time(), "device": device}
            data = json.dumps(me).encode() + b"\n"
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
        return fd
    raise OSError(errno.EAGAIN, f"{path} kept being replaced while it was being locked")


class _ProcessLocks:
    """The locks this process holds: path → [fd, users]."""

    def __init__(self) -> None:
        # re-entrant: a bus collected by the garbage collector while this thread holds it releases its claims
        self._mutex = threading.RLock()
        self._held: dict[str, list[int]] = {}

    def acquire(self, path: str, device: str) -> None:
        with self._mutex:
            entry = self._held.get(path)
            if entry is not None:
                entry[1] += 1
                return
            self._held[path] = [_lock(path, device), 1]

    def release(self, path: str) -> None:
        with self._mutex:
            entry = self._held.get(path)
            if entry is None:
                return
            entry[1] -= 1
            if entry[1] > 0:
                return
            del self._held[path]
            with contextlib.suppress(OSError):  # gone already, or another user's file in a sticky directory
                if _same_file(entry[0], path):
                    os.unlink(path)  # while still locked: nobody can have locked the file we remove
            os.close(entry[0])

    def held(self) -> dict[str, int]:
        with self._mutex:
            return {path: entry[1] for path, entry in self._held.items()}

    def forget_in_child(self) -> None:
        """After a fork: the child closes its copies (the parent still holds the locks) and owns nothing."""
        self._mutex = threading.RLock()  # another thread may have held it at the fork
        held, self._held = self._held, {}
        for fd, _ in held.values():
            with contextlib.suppress(OSError):
                os.close(fd)


_locks = _ProcessLocks()
os.register_at_fork(after_in_child=_locks.forget_in_child)


def acquire(path: str, device: str = "") -> None:
    """Hold the lock at ``path`` for this process (counted: one more user if it already holds it).

    Raises :class:`LockHeld` naming the owner if another process holds it, ``OSError`` if the file cannot be
    opened or locked at all.
    """
    _locks.acquire(path, device)


def release(path: str) -> None:
    """One user fewer; the last one removes the file and lets the lock go. Unknown paths are ignored."""
    _locks.release(path)


def held() -> dict[str, int]:
    """The lock files this process holds, with how many users each."""
    return _locks.held()
