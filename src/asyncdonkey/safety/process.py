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

**The car watches its guard too.** The guard stores its own heartbeat every pass of its loop (at least every
20 ms). The car's watchdog thread, which does not depend on the event loop, calls :meth:`SafetyProcess.check`
every ``CHECK_S``: a guard that has exited (``kill -9``, a crash) or whose heartbeat is older than the
heartbeat timeout (frozen: SIGSTOP, starved) is *lost*. Then, in this order: one log line naming it and why, the
throttle (every output that ``stops_motion``) to its safe state through the in-process path, and a new guard
started on the same shared state (off the watchdog thread: starting one takes tens of milliseconds). After
``MAX_RESTARTS`` losses in one drive the drive is stopped instead, with the reason ``"safety process lost"``: a
guard that keeps dying is a fault to look at, not to paper over. The report says how many times it was lost and
restarted, and why.

**Signals reach the guard even when the car cannot run its handler.** With :meth:`watch_signals` (installed by
``Vehicle.run_with_signals``), the interpreter's wakeup descriptor is a pipe the guard reads: the C-level signal
handler writes the signal's number there at once, even while C code holds the GIL. The Python handler, when it
runs, publishes the time by which the car will have ended (:meth:`exit_requested`). A car that has not run its
handler within ``exit_grace_s`` of the signal, or not ended by the time it published, is ended by the guard:
every safe state, one line saying why, SIGKILL.
"""

from __future__ import annotations

import json
import logging
import math
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from ..errors import AsyncdonkeyError
from .guard import PHASE_ENDING, PHASE_TICKING, SharedState

__all__ = ["GuardedOutput", "SafetyProcess", "SafetyProcessError"]

logger = logging.getLogger("asyncdonkey.safety")

GUARD_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "guard.py")

#: how often the car checks that its guard is alive (from the watchdog thread)
CHECK_S = 0.05
#: losses of the guard in one drive answered by a restart; the next one stops the drive
MAX_RESTARTS = 3
#: how long the guard may take to answer ``stop`` at the drive's end before it is killed
STOP_ANSWER_S = 1.5


class SafetyProcessError(AsyncdonkeyError, RuntimeError):
    """The safety process could not be started (it names the output or the reason)."""


@dataclass
class GuardedOutput:
    """One actuator the safety process covers: its name, its route (plain data) and the part, which is told
    when the guard has written its output (``output_overridden()``), so it writes its own target again.
    ``stops_motion``: the throttle; the guard serves it first, and the car stops it in-process when it loses
    its guard."""

    name: str
    route: dict[str, Any]
    part: Any
    stops_motion: bool = False


class SafetyProcess:
    """One guard process for one drive."""

    def __init__(
        self, outputs: Sequence[GuardedOutput], heartbeat_timeout_s: float, exit_grace_s: float | None = None
    ) -> None:
        if not outputs:
            raise ValueError("SafetyProcess: nothing to guard")
        self.outputs = list(outputs)
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        #: how long after a stop signal the car may go without running its handler before the guard ends it
        #: (``None``: the guard does not watch signals)
        self.exit_grace_s = exit_grace_s
        #: a guard whose heartbeat is older than this is frozen
        self.freeze_limit_s = max(self.heartbeat_timeout_s, 0.25)
        self.state, self._fd = SharedState.create(len(self.outputs))
        # the signal wakeup pipe: the guard reads, the interpreter's C-level handler writes (watch_signals)
        self._sig_r, self._sig_w = os.pipe()
        os.set_blocking(self._sig_w, False)
        self._old_wakeup: int | None = None
        self.proc: subprocess.Popen[bytes] | None = None
        self._seen_writes = 0
        self._beat = self.state.heartbeat_setter()
        self.resyncs = 0
        self.summary: dict[str, Any] | None = None
        #: why the guard was lost, each time (it is restarted up to MAX_RESTARTS times a drive)
        self.losses: list[str] = []
        self.restarts = 0
        #: called with a reason when the drive must stop because its guard cannot be kept (set by the drive)
        self.stop_drive: Callable[[str], None] | None = None
        self._lock = threading.Lock()
        self._restarting: threading.Thread | None = None
        self._stopping = False

    # ------------------------------------------------------------------------------------------ start
    def start(self, timeout_s: float = 10.0) -> None:
        """Spawn the guard and wait (blocking, so call it off the loop thread) until it has opened every bus."""
        self.proc = self._spawn(timeout_s)
        logger.info(
            "safety process %d guards %s (heartbeat timeout %.0f ms)",
            self.proc.pid,
            ", ".join(o.name for o in self.outputs),
            self.heartbeat_timeout_s * 1e3,
        )

    def _spawn(self, timeout_s: float) -> subprocess.Popen[bytes]:
        """A guard process on this drive's shared state, once it has said ``ready``."""
        config = {
            "car_pid": os.getpid(),
            "fd": self._fd,
            "signal_fd": self._sig_r,
            "exit_grace_s": self.exit_grace_s,
            "heartbeat_timeout_s": self.heartbeat_timeout_s,
            "first": [i for i, o in enumerate(self.outputs) if o.stops_motion],
            "routes": [_named(o) for o in self.outputs],
        }
        proc = subprocess.Popen(
            [sys.executable, "-I", GUARD_SCRIPT],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            pass_fds=(self._fd, self._sig_r),
            start_new_session=True,  # a Ctrl-C for the car's terminal must not reach the guard first
            close_fds=True,
        )
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.write(json.dumps(config).encode() + b"\n")
        proc.stdin.flush()
        line = _read_line(proc, timeout_s)
        if line != "ready":
            _kill(proc)
            why = line or f"no answer within {timeout_s:g} s"
            raise SafetyProcessError(
                f"safety process for {', '.join(o.name for o in self.outputs)} did not start: {why}"
            )
        return proc

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
        """``(deadline, landed)`` of the guard's trip of output ``i`` in progress (nan, nan while the guard is
        frozen or dead: a record nobody keeps up to date is not evidence of a safe output)."""
        if time.monotonic() - self.state.guard_beat() > self.freeze_limit_s:
            return math.nan, math.nan
        return self.state.last_event(i)

    def exit_requested(self, by: float) -> None:
        """The car was asked to stop (its signal handler ran) and will have ended by ``by`` (monotonic); past it,
        the guard ends the car. Safe from a signal handler: one 8-byte store."""
        self.state.set_exit_by(by)

    # ------------------------------------------------------------------------------------ signals
    def watch_signals(self) -> bool:
        """Point the interpreter's signal wakeup descriptor at the guard (main thread only; returns whether it
        did), so a stop signal reaches the guard even while C code holds the car's GIL."""
        if threading.current_thread() is not threading.main_thread() or self._old_wakeup is not None:
            return False
        try:
            self._old_wakeup = signal.set_wakeup_fd(self._sig_w, warn_on_full_buffer=False)
        except (ValueError, OSError):
            return False
        return True

    def unwatch_signals(self) -> None:
        """Give the wakeup descriptor back to whoever had it (the event loop)."""
        old, self._old_wakeup = self._old_wakeup, None
        if old is None or threading.current_thread() is not threading.main_thread():
            return
        try:
            signal.set_wakeup_fd(old)
        except (ValueError, OSError):
            pass

    # ---------------------------------------------------------------------- the car watches its guard
    def check(self, now: float) -> float:
        """Called from the watchdog thread: is the guard alive (not exited, heartbeat fresh)? If not, answer it
        (module docstring). Returns when to check again."""
        proc = self.proc
        if self._stopping or proc is None or self._restarting is not None:
            return now + CHECK_S
        status = proc.poll()
        age = time.monotonic() - self.state.guard_beat()
        if status is None and age <= self.freeze_limit_s:
            return now + CHECK_S
        if status is not None:
            why = f"exited (status {status})"
        else:
            why = f"frozen (no heartbeat for {age * 1e3:.0f} ms, limit {self.freeze_limit_s * 1e3:.0f} ms)"
        self._lost(proc, why)
        return now + CHECK_S

    def _lost(self, proc: subprocess.Popen[bytes], why: str) -> None:
        self.losses.append(why)
        restart = len(self.losses) <= MAX_RESTARTS
        what = (
            f"restarting it ({len(self.losses)} of {MAX_RESTARTS} restarts)"
            if restart
            else f"stopping the drive (lost {len(self.losses)} times)"
        )
        names = [o.name for o in self.outputs if o.stops_motion]
        logger.error(
            "safety process %d %s: %s to its safe state in-process; %s",
            proc.pid,
            why,
            ", ".join(names) or "nothing",
            what,
        )
        for o in self.outputs:
            if o.stops_motion:
                safe = getattr(o.part, "safe_state_sync", None)
                try:
                    if callable(safe):
                        safe()
                except Exception as exc:  # the watchdog retries its own writes; this one is logged
                    logger.error("safety process lost: %r could not be put in its safe state: %r", o.name, exc)
        if restart:
            t = threading.Thread(target=self._restart, args=(proc,), name="asyncdonkey-guard-restart", daemon=True)
            self._restarting = t
            t.start()
        elif self.stop_drive is not None:
            self._restarting = threading.current_thread()  # no more checks: the drive is ending
            self.stop_drive("safety process lost")

    def _restart(self, old: subprocess.Popen[bytes]) -> None:
        _kill(old)
        try:
            with self._lock:
                if self._stopping:
                    return
                self.proc = proc = self._spawn(10.0)
                self.restarts += 1
            logger.warning("safety process restarted: %d guards %s", proc.pid, ", ".join(o.name for o in self.outputs))
        except (SafetyProcessError, OSError) as exc:
            logger.error("safety process could not be restarted (%s); stopping the drive", exc)
            if self.stop_drive is not None:
                self.stop_drive("safety process lost")
            return
        finally:
            _close_pipes(old)
        self._restarting = None

    # -------------------------------------------------------------------------------------------- stop
    def stop(self, timeout_s: float = STOP_ANSWER_S) -> dict[str, Any]:
        """Tell the guard the drive is over (it writes every safe state once more) and collect its figures.

        Bounded: a guard that is frozen (its heartbeat stale) or does not answer within ``timeout_s`` is
        killed, and the figures are read from the shared state instead."""
        self._stopping = True
        self.unwatch_signals()
        restarting = self._restarting
        if restarting is not None and restarting is not threading.current_thread():
            restarting.join(timeout_s)
        with self._lock:
            proc = self.proc
        stats = [self.state.guard_stats(i) for i in range(len(self.outputs))]
        if proc is not None and proc.poll() is None:
            if time.monotonic() - self.state.guard_beat() > self.freeze_limit_s:
                logger.error("safety process %d is frozen at the drive's end; killing it", proc.pid)
                _kill(proc)
            else:
                stats = self._ask_to_stop(proc, timeout_s) or stats
        self._close()
        self.summary = _summary(self.outputs, stats, self.heartbeat_timeout_s, self.resyncs, self.losses, self.restarts)
        return self.summary

    def _ask_to_stop(self, proc: subprocess.Popen[bytes], timeout_s: float) -> list[dict[str, float]] | None:
        """``stop`` to the guard; its figures, or ``None`` (it is killed) if it does not answer in time."""
        try:
            assert proc.stdin is not None
            proc.stdin.write(b"stop\n")
            proc.stdin.flush()
            line = self._answer(proc, timeout_s)
            stats = json.loads(line)["slots"] if line.startswith("{") else None
            if stats is None:
                logger.error("safety process %d did not answer stop; killing it", proc.pid)
                _kill(proc)
                return None
            proc.wait(timeout_s)
            return stats  # type: ignore[no-any-return]
        except (OSError, ValueError, subprocess.TimeoutExpired) as exc:
            logger.error("safety process %d did not end cleanly (%r); killing it", proc.pid, exc)
            _kill(proc)
            return None

    def _answer(self, proc: subprocess.Popen[bytes], timeout_s: float) -> str:
        """The guard's answer line, waited for at most ``timeout_s``, and no longer than its heartbeat stays
        fresh (a guard frozen meanwhile will not answer: ``""``)."""
        end = time.monotonic() + timeout_s
        while True:
            line = _read_line(proc, min(CHECK_S, max(0.0, end - time.monotonic())))
            if line:
                return line
            now = time.monotonic()
            if now >= end or now - self.state.guard_beat() > self.freeze_limit_s or proc.poll() is not None:
                return ""

    def kill(self) -> None:
        self._stopping = True
        self.unwatch_signals()
        if self.proc is not None:
            _kill(self.proc)
        self._close()

    def _close(self) -> None:
        if self.proc is not None:
            _close_pipes(self.proc)
        # the wakeup pipe stays open while the interpreter may still write to it (not given back: not main thread)
        sig_w = self._sig_w if self._old_wakeup is None else -1
        for fd in (self._fd, self._sig_r, sig_w):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._fd = self._sig_r = self._sig_w = -1


def _named(o: GuardedOutput) -> dict[str, Any]:
    """The route as the guard gets it, named for its log lines: the part, then where its output is."""
    where = o.route.get("name")
    return {**o.route, "name": f"{o.name} ({where})" if where else o.name}


def _read_line(proc: subprocess.Popen[bytes], timeout_s: float) -> str:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    if not ready:
        return ""
    return proc.stdout.readline().decode(errors="replace").strip()


def _kill(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.kill()  # SIGKILL ends a stopped (SIGSTOP) process too
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:  # pragma: no cover - a process in uninterruptible sleep
            logger.error("safety process %d did not end after SIGKILL", proc.pid)


def _close_pipes(proc: subprocess.Popen[bytes]) -> None:
    for f in (proc.stdin, proc.stdout):
        if f is not None:
            try:
                f.close()
            except OSError:
                pass


def _summary(
    outputs: Sequence[GuardedOutput],
    stats: Sequence[dict[str, float]],
    timeout_s: float,
    resyncs: int,
    losses: Sequence[str] = (),
    restarts: int = 0,
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
        "lost": len(losses),
        "lost_why": list(losses),
        "restarts": restarts,
    }


def heartbeat_timeout_for(windows: Sequence[float | None], rate_hz: float) -> float:
    """The heartbeat timeout: the shortest failsafe window among the actuators (0.25 s if none has one), but
    never less than three tick periods, so a loop that ticks on time is never taken for a stopped one."""
    finite = [w for w in windows if w is not None and math.isfinite(w) and w > 0]
    window = min(finite) if finite else 0.25
    return max(window, 3.0 / rate_hz)
