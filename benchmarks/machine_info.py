"""One line describing the machine a benchmark ran on (figures mean little without it)."""

from __future__ import annotations

import os
import platform
from importlib import metadata
from pathlib import Path


def donkeycar_version() -> str | None:
    """The installed Donkeycar's version (5.3.x on Python 3.11, 5.4.x on 3.12-3.13), or ``None``; read from the
    package metadata, so Donkeycar's import banner stays out of the output."""
    try:
        return metadata.version("donkeycar")
    except metadata.PackageNotFoundError:
        return None


def donkeycar_label() -> str:
    """``"Donkeycar 5.4.0"``: how tables name the Donkeycar the comparison ran against."""
    v = donkeycar_version()
    return f"Donkeycar {v}" if v else "Donkeycar"


def describe(with_load: bool = False) -> str:
    """CPU model, core count, OS, Python; with ``with_load`` the load average, since a busy machine's
    figures are worse and should say so."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    text = (
        f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.release()}, Python {platform.python_version()}"
    )
    if with_load and hasattr(os, "getloadavg"):
        text += "; load average at start " + ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return text
