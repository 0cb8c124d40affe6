"""The car's side of the safety process: start it, heartbeat it every tick, publish command deadlines.

:mod:`asyncdonkey.safety.guard` is the program that runs beside the car; this module is what the drive uses to
run it. A drive on a real loop starts one when at least one actuator has a route another process can take to
its output (a PCA9685 channel on a real bus, or on a served simulator in tests); see
:attr:`asyncdonkey.Vehicle.safety_process` to require it or turn it off.

What crosses to the guard, and when:

* at the start, one JSON line on its stdin: each output's route (bus, address, register and the bytes of the
  safe pulse *the drive started with*, so a calibration changed during the drive cannot redefine "safe"), the
  heartbeat timeout and the car's pid; the guard answers ``ready`` once it has opened every bus;
* every tick, the heartbeat: one 8-byte store into shared memory, and one 8-byte load of the guard's write
  total (the per-tick cost is in ``benchmarks/safety.py``). A tick that awaits a part (``executor=True``, an
  async ``run``) leaves the loop free meanwhile, so before the await it stores a heartbeat that far ahead as the
  part's ``timeout=`` (or forever): a slow pilot is not a stopped loop, and its commands' deadlines still count;
  a sync part that holds the loop thread is, and the guard acts one heartbeat timeout after the tick began;
* every command an actuator applies, its deadline (two stores);
* at the end, ``stop`` on its stdin; it writes every safe state once more and answers with its figures.

The car never waits for the guard during the drive, and the guard never waits for the car: if the car dies,
the guard notices through the car's pidfd (or the pipe closing) at once.
"""

from __future__ import annotations

import json
import logging
import math
import os
import select
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from .guard import PHASE_ENDING, PHASE_TICKING, SharedState

__all__ = ["GuardedOutput", "SafetyProcess", "SafetyProcessError"]

logger = logging.getLogger("asyncdonkey.safety")

GUARD_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "guard.py")


class SafetyProcessError(RuntimeError):
    """The safety process could not be started (it names the output or the reason)."""


@dataclass
class GuardedOutput:
    """One actuator the safety process covers: its name, its route (plain data) and the part, which is told
    when the guard has written its output (``output_overridden()``), so it writes its own target again."""

    name: str
    route: dict[str, Any]
    part: Any


class SafetyProcess:
    """One guard process for one drive."""

    def __init__(self, outputs: Sequence[GuardedOutput], heartbeat_timeout_s: float) -> None:
        if not outputs:
            raise ValueError("SafetyProcess: nothing to guard")
        self.outputs = list(outputs)
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self.state, self._fd = SharedState.create(len(self.outputs))
        self.proc: subprocess.Popen[bytes] | None = None
        self._seen_writes = 0
        self._beat = self.state.heartbeat_setter()
        self.resyncs = 0
        self.summary: dict[str, Any] | None = None

    # ------------------------------------------------------------------------------------------ start
    def start(self, timeout_s: float = 10.0) -> None:
        """Spawn the guard and wait (blocking, so call it off the loop thread) until it has opened every bus."""
        config = {
            "car_pid": os.getpid(),
            "fd": self._fd,
            "heartbeat_timeout_s": self.heartbeat_timeout_s,
            "routes": [o.route for o in self.outputs],
        }
        self.proc = proc = subprocess.Popen(
            [sys.executable, "-I", GUARD_SCRIPT],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            pass_fds=(self._fd,),
            start_new_session=True,  # a Ctrl-C for the car's terminal must not reach the guard first
            close_fds=True,
        )
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.write(json.dumps(config).encode() + b"\n")
        proc.stdin.flush()
        line = self._read_line(timeout_s)
        if line != "ready":
            self.kill()
            why = line or f"no answer within {timeout_s:g} s"
            raise SafetyProcessError(
                f"safety process for {', '.join(o.name for o in self.outputs)} did not start: {why}"
            )
        logger.info(
            "safety process %d guards %s (heartbeat timeout %.0f ms)",
            proc.pid,
            ", ".join(o.name for o in self.outputs),
            self.heartbeat_timeout_s * 1e3,
        )

    def _read_line(self, timeout_s: float) -> str:
        proc = self.proc
        assert proc is not None and proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
        if not ready:
            return ""
        return proc.stdout.readline().decode(errors="replace").strip()

    # ------------------------------------------------------------------------------------ during a drive
    def deadline_setter(self, i: int) -> Callable[[float], None]:
        """``set(deadline)`` for output ``i``: called by its actuator for every command it applies."""
        setter: Callable[[float], None] = self.state.deadline_setter(i)
        return setter

    def ticking(self) -> None:
        """The ticks begin: from now on a heartbeat older than the timeout means the loop has stopped."""
        self._beat(time.monotonic())
        self.state.set_phase(PHASE_TICKING)

    def beat(self, now: float) -> None:
        """The tick's heartbeat (``now`` on the runtime clock, which is the monotonic clock on a real loop).

        When the guard has written an output since the last tick, each guarded part is told, so that its writer
        puts its own target (the safe one while its command is stale) back on the output."""
        writes = self._beat(now)
        if writes != self._seen_writes:
            self._seen_writes = writes
            self.resyncs += 1
            for o in self.outputs:
                overridden = getattr(o.part, "output_overridden", None)
                if overridden is not None:
                    overridden()

    def ending(self) -> None:
        """The ticks have ended: shutdown runs; command deadlines still count, the heartbeat no longer does."""
        self.state.set_phase(PHASE_ENDING)

    def last_event(self, i: int) -> tuple[float, float]:
        return self.state.last_event(i)

    # -------------------------------------------------------------------------------------------- stop
    def stop(self, timeout_s: float = 3.0) -> dict[str, Any]:
        """Tell the guard the drive is over (it writes every safe state once more) and collect its figures."""
        proc = self.proc
        stats = [self.state.guard_stats(i) for i in range(len(self.outputs))]
        if proc is not None and proc.poll() is None:
            try:
                assert proc.stdin is not None
                proc.stdin.write(b"stop\n")
                proc.stdin.flush()
                line = self._read_line(timeout_s)
                if line.startswith("{"):
                    stats = json.loads(line)["slots"]
                proc.wait(timeout_s)
            except (OSError, ValueError, subprocess.TimeoutExpired) as exc:
                logger.error("safety process %d did not end cleanly (%r); killing it", proc.pid, exc)
                self.kill()
        self._close()
        self.summary = _summary(self.outputs, stats, self.heartbeat_timeout_s, self.resyncs)
        return self.summary

    def kill(self) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(5.0)
        self._close()

    def _close(self) -> None:
        proc = self.proc
        if proc is not None:
            for f in (proc.stdin, proc.stdout):
                if f is not None:
                    try:
                        f.close()
                    except OSError:
                        pass
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def _summary(
    outputs: Sequence[GuardedOutput], stats: Sequence[dict[str, float]], timeout_s: float, resyncs: int
) -> dict[str, Any]:
    """The report's view of what the guard did: totals, and per output only where it acted."""
    per = {
        o.name: {
            "events": int(s["events"]),
            "writes": int(s["writes"]),
            "failed_attempts": int(s["failed_attempts"]),
            "unsafe_max_ms": float(s["unsafe_max_s"]) * 1e3,
        }
        for o, s in zip(outputs, stats, strict=True)
    }
    return {
        "outputs": [o.name for o in outputs],
        "heartbeat_timeout_ms": timeout_s * 1e3,
        "events": sum(p["events"] for p in per.values()),
        "failed_attempts": sum(p["failed_attempts"] for p in per.values()),
        "resyncs": resyncs,
        "acted": {k: v for k, v in per.items() if v["events"] or v["failed_attempts"]},
    }


def heartbeat_timeout_for(windows: Sequence[float | None], rate_hz: float) -> float:
    """The heartbeat timeout: the shortest failsafe window among the actuators (0.25 s if none has one), but
    never less than three tick periods, so a loop that ticks on time is never taken for a stopped one."""
    finite = [w for w in windows if w is not None and math.isfinite(w) and w > 0]
    window = min(finite) if finite else 0.25
    return max(window, 3.0 / rate_hz)
