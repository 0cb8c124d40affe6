"""The writer's only door to the file system, so tests can make the disk slow, full or flaky.

Every file operation of :class:`~asyncdonkey.parts.tub.TubWriter`'s writer thread goes through a
:class:`TubFileIO`. Subclass it and pass ``file_io=`` to inject faults: a ``write_file`` that sleeps 200 ms is
a stalling SD card; one that raises ``OSError(ENOSPC)`` is a full disk. The default implementation is plain
``os`` calls.

Durability primitives: :meth:`TubFileIO.sync_filesystem` flushes the whole file system holding a file in one
call (Linux ``syncfs(2)``), which is much cheaper than one ``fsync`` per image when a sync point covers many
records; where it is unavailable the writer falls back to ``fdatasync`` per file plus ``fsync`` of the
directories (:meth:`sync_path`, :meth:`sync_dir`).
"""

from __future__ import annotations

import ctypes
import os

from ...clock._libc import libc_function

__all__ = ["TubFileIO", "with_filename"]


_SYNCFS = libc_function("syncfs", (ctypes.c_int,))
_fdatasync = getattr(os, "fdatasync", os.fsync)


def with_filename(exc: OSError, path: str) -> OSError:
    """``exc`` naming ``path`` when it names no file (``os.write`` and ``fsync`` errors do not), so that the
    warning a full disk causes says which file could not be written."""
    if exc.filename is not None or exc.errno is None:
        return exc
    return OSError(exc.errno, exc.strerror or str(exc), path)


class TubFileIO:
    """Plain file operations; override any method to simulate a slow or failing disk."""

    #: Whether :meth:`sync_filesystem` works here (Linux). Set to False to force per-file fsyncs.
    has_syncfs: bool = _SYNCFS is not None

    def write_file(self, path: str, data: bytes) -> None:
        """Create or truncate ``path`` and write all of ``data`` (no fsync)."""
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            self._write_all(fd, data)
        finally:
            os.close(fd)

    def open_append(self, path: str) -> int:
        """Open ``path`` for appending (created if missing); returns the descriptor."""
        return os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def append(self, fd: int, data: bytes) -> None:
        """Append all of ``data`` to ``fd``; a short write that cannot complete raises ``OSError``."""
        self._write_all(fd, data)

    def truncate(self, fd: int, size: int) -> None:
        os.ftruncate(fd, size)

    def close(self, fd: int) -> None:
        os.close(fd)

    def replace(self, src: str, dst: str) -> None:
        """Atomically rename ``src`` over ``dst`` (same directory)."""
        os.replace(src, dst)

    def remove(self, path: str) -> None:
        os.remove(path)

    def sync_file(self, fd: int) -> None:
        """Make ``fd``'s data durable."""
        _fdatasync(fd)

    def sync_path(self, path: str) -> None:
        """Make the data of the file at ``path`` durable."""
        fd = os.open(path, os.O_RDONLY)
        try:
            _fdatasync(fd)
        finally:
            os.close(fd)

    def sync_dir(self, path: str) -> None:
        """Make the entries of directory ``path`` (new files, renames) durable."""
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def sync_filesystem(self, fd: int) -> None:
        """Flush everything dirty on the file system holding ``fd`` (Linux ``syncfs``)."""
        if _SYNCFS is None:
            raise OSError("syncfs is not available on this platform")
        if _SYNCFS(fd) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"syncfs: {os.strerror(err)}")

    @staticmethod
    def _write_all(fd: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            if n <= 0:  # pragma: no cover - os.write raises instead on real files
                raise OSError("write made no progress")
            view = view[n:]
