"""The safety process: a second, independent path to every actuator, outside the car's interpreter.

Why a process. The watchdog thread in the car's process is the fast first line, but it shares that process's
fate: C code that holds the GIL (a catastrophic regular expression, a ``sorted()`` of a huge list, a native
library that never releases it) freezes it with everything else, many busy Python threads can starve it past
its window, and a process killed with SIGKILL or crashing in native code runs no code at all, while a PCA9685
keeps generating its last pulse. This program runs in a process of its own, with no user code in it and no
GIL shared, and owns its own handle on each actuator's bus. It writes an actuator's safe state when

* the command deadline the car published for it passes without a fresh command,
* the car's heartbeat (written once a tick) stops for longer than the heartbeat timeout, or
* the car process is gone (its pidfd turns readable, the command pipe closes, or the parent changes),

and keeps it: while tripped it reads the output back now and then and writes the safe state again if a stale
write from the car landed after it, until the car resumes with a fresh command. A safe-state write that fails
(a NACK, a bus error) is retried with a bounded backoff until it lands, each attempt counted. Outputs are served
in turn, the throttle first: one output's retries never hold back another's first write.

It also ends a car that cannot end itself. The car's signal handling points the interpreter's wakeup descriptor
(``signal.set_wakeup_fd``) at a pipe this process reads, so a SIGINT, SIGTERM or SIGHUP reaches the guard from the
C-level handler at once, even while C code holds the car's GIL and no Python handler can run. When the car's
Python handler runs, it publishes the time by which it will have ended (its stop grace plus its shutdown
deadline). If the car has not ended by then, or has not run its handler within the exit grace of the signal,
the guard writes every safe state, says why in one line, and kills the car with SIGKILL.

The car watches the guard in turn: the guard stores its own heartbeat (``guard_beat``) on every pass of its loop
(at least every ``POLL_S``), which the car's watchdog thread checks (:mod:`asyncdonkey.safety.process`).

It imports only the standard library and smbus2 (a test's served I2C simulator is imported only when a route
names one), so it starts in tens of milliseconds and holds a few MB. It is started as a script by path
(``python -I guard.py``) with the car's shared state passed as an inherited memory file descriptor; the same
file is also the ``asyncdonkey.safety.guard`` module, which the car imports for the shared layout.

The shared state is a small memory-mapped file: a header (the heartbeat and the drive's phase, the total
of the guard's safe writes, which the car checks once a tick to rewrite its outputs after the guard touched
them, the guard's own heartbeat, and the time by which a car asked to stop will have ended) and one slot per
actuator (the command deadline and a command count from the car; the guard's counts,
unsafe times and its latest event from the guard). Each field has one writer, and each is one aligned 8-byte
store, so neither side ever waits for the other.
"""

from __future__ import annotations

import json
import math
import mmap
import os
import select
import signal
import struct
import sys
import time
from typing import Any

__all__ = ["HEADER_SIZE", "PHASE_ENDING", "PHASE_STARTING", "PHASE_TICKING", "SLOT_SIZE", "SharedState"]

MAGIC = b"ADSG"
VERSION = 2
HEADER_SIZE = 64
SLOT_SIZE = 128
#: the drive has not ticked yet: no heartbeat to watch
PHASE_STARTING = 0
#: the drive is ticking: a heartbeat older than the timeout means the loop has stopped
PHASE_TICKING = 1
#: the ticks have ended and shutdown runs: deadlines still count, the heartbeat does not
PHASE_ENDING = 2

# header fields (offsets)
_H_MAGIC = 0  # 4s + u32 version
_H_HEARTBEAT = 8  # f64, car: monotonic time of the latest tick
_H_PHASE = 16  # u64, car
_H_WRITES = 24  # u64, guard: safe writes landed, all slots
_H_GUARD_BEAT = 32  # f64, guard: monotonic time of its latest pass (the car checks it is alive)
_H_EXIT_BY = 40  # f64, car: a stop was asked for, and the car will have ended by then (inf: none asked)
# slot fields (offsets within a slot)
_S_DEADLINE = 0  # f64, car: when the current command goes stale (inf: no failsafe)
_S_SEQ = 8  # u64, car: commands applied
_S_WRITES = 16  # u64, guard: safe writes landed
_S_FAILED = 24  # u64, guard: safe-write attempts that failed
_S_EVENTS = 32  # u64, guard: times tripped
_S_UNSAFE_TOTAL = 40  # f64, guard: seconds from the trip's cause to its safe write landing, summed
_S_UNSAFE_MAX = 48  # f64, guard
_S_LAST_CAUSE = 56  # f64, guard: the deadline (or heartbeat timeout) of the latest trip
_S_LAST_LANDED = 64  # f64, guard: when its safe write landed, while it holds the output safe (else nan)
_S_TRIP_DEADLINE = 72  # f64, guard: the command deadline in force when it tripped (inf: none)

_D = struct.Struct("<d")
_Q = struct.Struct("<Q")


class SharedState:
    """The shared memory between the car and its safety process; both sides use this one layout."""

    def __init__(self, buf: mmap.mmap, slots: int) -> None:
        self.buf = buf
        self.slots = slots

    @staticmethod
    def size(slots: int) -> int:
        return HEADER_SIZE + SLOT_SIZE * slots

    @classmethod
    def create(cls, slots: int) -> tuple[SharedState, int]:
        """A fresh state in an anonymous memory file; returns it and the descriptor to pass to the guard."""
        size = cls.size(slots)
        if hasattr(os, "memfd_create"):
            fd = os.memfd_create("asyncdonkey-safety", 0)
        else:  # pragma: no cover - Linux has memfd_create; elsewhere a deleted temporary file does the same
            import tempfile

            with tempfile.TemporaryFile() as f:
                fd = os.dup(f.fileno())
        os.ftruncate(fd, size)
        state = cls(mmap.mmap(fd, size), slots)
        state.buf[_H_MAGIC : _H_MAGIC + 8] = MAGIC + struct.pack("<I", VERSION)
        _D.pack_into(state.buf, _H_EXIT_BY, math.inf)
        _D.pack_into(state.buf, _H_GUARD_BEAT, -math.inf)
        for i in range(slots):
            state._set_d(i, _S_DEADLINE, math.inf)
            state._set_d(i, _S_LAST_CAUSE, math.nan)
            state._set_d(i, _S_LAST_LANDED, math.nan)
            state._set_d(i, _S_TRIP_DEADLINE, math.nan)
        return state, fd

    @classmethod
    def attach(cls, fd: int, slots: int) -> SharedState:
        size = cls.size(slots)
        state = cls(mmap.mmap(fd, size), slots)
        if bytes(state.buf[:4]) != MAGIC:
            raise ValueError("not an asyncdonkey safety state")
        return state

    # -------------------------------------------------------------------------------------- access
    def _off(self, slot: int, field: int) -> int:
        return HEADER_SIZE + SLOT_SIZE * slot + field

    def _get_d(self, slot: int, field: int) -> float:
        return float(_D.unpack_from(self.buf, self._off(slot, field))[0])

    def _set_d(self, slot: int, field: int, value: float) -> None:
        _D.pack_into(self.buf, self._off(slot, field), value)

    def _get_q(self, slot: int, field: int) -> int:
        return int(_Q.unpack_from(self.buf, self._off(slot, field))[0])

    def _set_q(self, slot: int, field: int, value: int) -> None:
        _Q.pack_into(self.buf, self._off(slot, field), value)

    # car side
    def deadline_setter(self, slot: int) -> Any:
        """``set(deadline)`` for one slot: the deadline and one more command, two stores (the car's hot path)."""
        buf = self.buf
        d_off = self._off(slot, _S_DEADLINE)
        q_off = self._off(slot, _S_SEQ)
        pack_d, pack_q, unpack_q = _D.pack_into, _Q.pack_into, _Q.unpack_from

        def set_deadline(deadline: float) -> None:
            pack_q(buf, q_off, unpack_q(buf, q_off)[0] + 1)
            pack_d(buf, d_off, deadline)

        return set_deadline

    def heartbeat_setter(self) -> Any:
        """``beat(t) -> writes_total``: stores the heartbeat and returns the guard's safe-write total, so the
        car can tell in the same call whether the guard has touched an output since its last tick."""
        buf = self.buf
        pack, unpack = _D.pack_into, _Q.unpack_from

        def beat(t: float) -> int:
            pack(buf, _H_HEARTBEAT, t)
            return unpack(buf, _H_WRITES)[0]  # type: ignore[no-any-return]

        return beat

    def set_phase(self, phase: int) -> None:
        _Q.pack_into(self.buf, _H_PHASE, phase)

    def set_exit_by(self, t: float) -> None:
        """A stop was asked for: the car will have ended by ``t`` (monotonic), or the guard ends it."""
        _D.pack_into(self.buf, _H_EXIT_BY, t)

    def guard_beat(self) -> float:
        """The guard's latest pass (monotonic; ``-inf`` before its first)."""
        return float(_D.unpack_from(self.buf, _H_GUARD_BEAT)[0])

    # guard side
    def heartbeat(self) -> float:
        return float(_D.unpack_from(self.buf, _H_HEARTBEAT)[0])

    def phase(self) -> int:
        return int(_Q.unpack_from(self.buf, _H_PHASE)[0])

    def deadline(self, slot: int) -> float:
        return self._get_d(slot, _S_DEADLINE)

    def seq(self, slot: int) -> int:
        return self._get_q(slot, _S_SEQ)

    def writes_total(self) -> int:
        return int(_Q.unpack_from(self.buf, _H_WRITES)[0])

    def exit_by(self) -> float:
        return float(_D.unpack_from(self.buf, _H_EXIT_BY)[0])

    def set_guard_beat(self, t: float) -> None:
        _D.pack_into(self.buf, _H_GUARD_BEAT, t)

    def guard_stats(self, slot: int) -> dict[str, float]:
        """What the guard did for one slot (read by the car for its report)."""
        return {
            "events": self._get_q(slot, _S_EVENTS),
            "writes": self._get_q(slot, _S_WRITES),
            "failed_attempts": self._get_q(slot, _S_FAILED),
            "unsafe_total_s": self._get_d(slot, _S_UNSAFE_TOTAL),
            "unsafe_max_s": self._get_d(slot, _S_UNSAFE_MAX),
        }

    def last_event(self, slot: int) -> tuple[float, float]:
        """``(deadline, landed)`` of the guard's trip of this slot: the command deadline in force when it tripped
        (whatever the trip's cause, the deadline or the heartbeat) and when its latest safe write of that trip
        landed, while the trip lasts (nan before it has landed, and once the guard has let go)."""
        return self._get_d(slot, _S_TRIP_DEADLINE), self._get_d(slot, _S_LAST_LANDED)


# ------------------------------------------------------------------------------------- the outputs


class Output:
    """One actuator's output as the guard reaches it: a register block on an I2C chip, through its own handle."""

    def __init__(self, route: dict[str, Any]) -> None:
        self.name = str(route.get("name", "output"))
        self.address = int(route["address"])
        self.register = int(route["register"])
        self.data = [int(b) for b in route["data"]]
        ai = route.get("auto_increment")
        self.ai_register: int | None = int(ai[0]) if ai else None
        self.ai_mask = int(ai[1]) if ai else 0
        self.smbus = open_smbus(route["smbus"])

    def write_safe(self) -> None:
        """Put the safe bytes on the chip; one block write when the chip auto-increments, else byte by byte."""
        bus, addr = self.smbus, self.address
        if self.ai_register is None or bus.read_byte_data(addr, self.ai_register) & self.ai_mask:
            bus.write_i2c_block_data(addr, self.register, self.data)
        else:
            for i, b in enumerate(self.data):
                bus.write_byte_data(addr, self.register + i, b)

    def shows_safe(self) -> bool:
        return list(self.smbus.read_i2c_block_data(self.address, self.register, len(self.data))) == self.data

    def close(self) -> None:
        try:
            self.smbus.close()
        except OSError:
            pass


def open_smbus(spec: dict[str, Any]) -> Any:
    """An SMBus handle of this process's own for a bus spec (``I2CBus.cross_process_spec``).

    A real bus is a device path. Anything else names its opener as ``"module:function"`` with its arguments (a
    test's served register models: ``asyncdonkey.testing.i2c_models:open_served_smbus``), imported only then:
    the guard itself depends on nothing but smbus2, and the car, which wrote the spec, chose the opener."""
    if "path" in spec:
        import smbus2

        return smbus2.SMBus(spec["path"])
    opener = spec.get("opener")
    if isinstance(opener, str) and ":" in opener:
        import importlib

        module, _, name = opener.partition(":")
        return getattr(importlib.import_module(module), name)(*spec.get("args", ()))
    raise ValueError(f"unknown bus spec {spec!r}")


# ------------------------------------------------------------------------------------------ the guard

#: the longest the guard sleeps: a deadline can move earlier without telling it (a command with an older origin);
#: it is also the period of the guard's own heartbeat, which the car checks
POLL_S = 0.02
#: how often a tripped output is read back, to catch a stale write from the car that landed after the safe one
VERIFY_S = 0.1
#: the retry backoff of a failed safe write: first pause, cap
RETRY_FIRST_S = 0.002
RETRY_MAX_S = 0.05
#: after the car is gone: how long to keep retrying a safe write that will not land before giving up
ORPHAN_RETRY_S = 30.0
#: at the drive's normal end: how long the last safe writes may take before the guard answers the car
STOP_RETRY_S = 0.5
#: the signals that ask the car to stop (their numbers arrive on the wakeup pipe)
STOP_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM, signal.SIGHUP})


class _Slot:
    __slots__ = ("cause", "failed", "next_attempt", "next_verify", "out", "pending", "seq_at_trip", "tripped")

    def __init__(self, out: Output) -> None:
        self.out = out
        self.tripped = False
        self.pending = False  # tripped, and the safe write has not landed yet
        self.cause = 0.0
        self.seq_at_trip = 0
        self.failed = 0  # consecutive failed attempts of the pending write
        self.next_attempt = 0.0
        self.next_verify = math.inf


def _backoff(failed: int) -> float:
    return float(min(RETRY_FIRST_S * 2 ** (failed - 1), RETRY_MAX_S))


class Guard:
    """The guard's state and decisions; :func:`main` runs it.

    ``first`` lists the slots to serve first (the throttle: what moves the car); every pass serves them, then
    the others, each one attempt at a time, so a NACKing output's retries never hold back another's write."""

    def __init__(
        self, state: SharedState, outputs: list[Output], heartbeat_timeout_s: float, first: tuple[int, ...] = ()
    ) -> None:
        self.state = state
        self.slots = [_Slot(o) for o in outputs]
        self.order = [i for i in first if 0 <= i < len(outputs)]
        self.order += [i for i in range(len(outputs)) if i not in self.order]
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.writes_total = state.writes_total()  # a restarted guard counts on from its predecessor
        for i in range(len(outputs)):  # and holds nothing safe yet, whatever its predecessor held
            state._set_d(i, _S_LAST_LANDED, math.nan)
        self._log_at: dict[str, float] = {}

    def log(self, key: str, msg: str, every_s: float = 1.0) -> None:
        now = time.monotonic()
        if now - self._log_at.get(key, -math.inf) >= every_s:
            self._log_at[key] = now
            print(f"asyncdonkey safety process: {msg}", file=sys.stderr, flush=True)

    def _cause(self, i: int, now: float) -> float | None:
        """When slot ``i`` became unsafe (its deadline, or the heartbeat's timeout), or ``None`` if it is not."""
        st = self.state
        deadline = st.deadline(i)
        cause = deadline if deadline <= now else None
        if st.phase() == PHASE_TICKING:
            hb_due = st.heartbeat() + self.heartbeat_timeout_s
            if hb_due <= now and (cause is None or hb_due < cause):
                cause = hb_due
        return cause

    def step(self, now: float) -> float:
        """Check every slot (the first ones first) and act; returns when to look again."""
        wake = now + POLL_S
        st = self.state
        st.set_guard_beat(now)
        for i in self.order:
            s = self.slots[i]
            cause = self._cause(i, now)
            if cause is None:
                if s.tripped:
                    # its deadline is in the future again (a fresh command) and the loop ticks: the car has it
                    s.tripped = s.pending = False
                    s.next_verify = math.inf
                    st._set_d(i, _S_LAST_LANDED, math.nan)  # no longer holding it safe
                deadline = st.deadline(i)
                if deadline < wake:
                    wake = deadline
                continue
            if not s.tripped:
                s.tripped = s.pending = True
                s.cause, s.seq_at_trip, s.failed, s.next_attempt = cause, st.seq(i), 0, now
                st._set_q(i, _S_EVENTS, st._get_q(i, _S_EVENTS) + 1)
                st._set_d(i, _S_LAST_CAUSE, cause)
                st._set_d(i, _S_TRIP_DEADLINE, st.deadline(i))
                st._set_d(i, _S_LAST_LANDED, math.nan)
            if s.pending and now >= s.next_attempt:
                self._attempt(i, s, now)
            elif not s.pending and now >= s.next_verify:
                self._verify(i, s, now)
            wake = min(wake, s.next_attempt if s.pending else s.next_verify)
        if st.phase() == PHASE_TICKING:
            wake = min(wake, st.heartbeat() + self.heartbeat_timeout_s)
        return wake

    def _attempt(self, i: int, s: _Slot, now: float) -> None:
        st = self.state
        try:
            s.out.write_safe()
        except OSError as exc:
            s.failed += 1
            st._set_q(i, _S_FAILED, st._get_q(i, _S_FAILED) + 1)
            s.next_attempt = time.monotonic() + _backoff(s.failed)
            self.log(f"fail{i}", f"{s.out.name}: safe-state write failed (attempt {s.failed}), retrying: {exc}")
            return
        landed = time.monotonic()
        s.pending = False
        s.next_verify = landed + VERIFY_S
        unsafe = max(0.0, landed - s.cause)
        st._set_d(i, _S_LAST_LANDED, landed)
        st._set_d(i, _S_UNSAFE_TOTAL, st._get_d(i, _S_UNSAFE_TOTAL) + unsafe)
        st._set_d(i, _S_UNSAFE_MAX, max(st._get_d(i, _S_UNSAFE_MAX), unsafe))
        st._set_q(i, _S_WRITES, st._get_q(i, _S_WRITES) + 1)
        self.writes_total += 1
        _Q.pack_into(st.buf, _H_WRITES, self.writes_total)
        tries = f" after {s.failed + 1} attempts" if s.failed else ""
        self.log(f"trip{i}", f"{s.out.name}: safe state written{tries}, {unsafe * 1e3:.0f} ms after it was due")

    def _verify(self, i: int, s: _Slot, now: float) -> None:
        """Tripped and written: if a driving write has landed since, and the car still has no fresh command
        (checked again after the read, so a fresh command's write is never undone), write the safe state again."""
        s.next_verify = now + VERIFY_S
        try:
            safe = s.out.shows_safe()
        except OSError:
            return  # the next look retries; a failed read is no reason to write
        if not safe and self._cause(i, time.monotonic()) is not None and self.state.seq(i) == s.seq_at_trip:
            s.pending, s.failed, s.next_attempt = True, 0, now
            self._attempt(i, s, now)

    def all_safe(self, give_up_s: float, why: str, quiet: bool = False) -> bool:
        """Every output to its safe state at once: the first ones first, then each still failing retried in turn
        on its own backoff, until all have landed or ``give_up_s`` has passed. Says in one line what is safe
        and what is not (and why) after the first round if any failed, and in one line how it ended. Returns
        whether every output is safe. ``quiet``: no line when every output landed at its first attempt."""
        st = self.state
        start = time.monotonic()
        until = start + give_up_s
        pending = list(self.order)
        attempts = dict.fromkeys(pending, 0)
        next_at = dict.fromkeys(pending, start)
        errors: dict[int, str] = {}
        said = False
        while pending:
            st.set_guard_beat(time.monotonic())  # alive, for the car: retrying is not being frozen
            for i in list(pending):
                if time.monotonic() < next_at[i]:
                    continue
                s = self.slots[i]
                try:
                    s.out.write_safe()
                except OSError as exc:
                    attempts[i] += 1
                    errors[i] = f"{exc}"
                    st._set_q(i, _S_FAILED, st._get_q(i, _S_FAILED) + 1)
                    next_at[i] = time.monotonic() + _backoff(attempts[i])
                    continue
                pending.remove(i)
                if attempts[i]:
                    self.log(f"late{i}", f"{s.out.name}: safe state written after {attempts[i] + 1} attempts", 0)
            if not pending:
                break
            if not said:
                said = True
                self.log("unsafe", f"{why}: {self._split(pending, errors)}; retrying for up to {give_up_s:g} s", 0)
            now = time.monotonic()
            if now >= until:
                names = ", ".join(f"{self.slots[i].out.name} ({attempts[i]} attempts)" for i in pending)
                self.log("gave", f"{why}: gave up after {give_up_s:g} s: NOT in its safe state: {names}", 0)
                return False
            time.sleep(max(0.0, min(min(next_at[i] for i in pending), until) - now))
        if not quiet or said:
            self.log("end", f"{why}: every output written to its safe state", 0)
        return True

    def _split(self, pending: list[int], errors: dict[int, str]) -> str:
        safe = [self.slots[i].out.name for i in self.order if i not in pending]
        bad = "; ".join(f"{self.slots[i].out.name} NOT safe ({errors.get(i, '?')})" for i in pending)
        return (f"{', '.join(safe)} in its safe state; " if safe else "") + bad


class ExitWatch:
    """When to end a car that was asked to stop and has not ended.

    A stop signal's number arrives on the wakeup pipe from the car's C-level handler (so even while C code
    holds the car's GIL); the car has ``grace_s`` to run its Python handler, which publishes the time by which
    it will have ended (``exit_by`` in the shared state: its stop grace plus its shutdown deadline). Past that
    time, or past the grace without it, the car is ended. Signals after the first change nothing: a car that ran
    its handler answers a second one itself (it exits at once), and the car's own stop re-delivers SIGINT to
    interrupt a part that holds its loop."""

    def __init__(self, state: SharedState, grace_s: float | None) -> None:
        self.state = state
        self.grace_s = grace_s
        self.signalled_at = math.inf
        self.signal_name = ""
        #: the car has been ended: nothing more to do but see it go
        self.ended = False

    def signalled(self, data: bytes, now: float) -> None:
        if self.grace_s is None or math.isfinite(self.signalled_at):
            return
        for b in data:
            try:
                sig = signal.Signals(b)
            except ValueError:
                continue
            if sig in STOP_SIGNALS:
                self.signalled_at, self.signal_name = now, sig.name
                return

    def due(self) -> float:
        """When to end the car (inf: not asked to stop, or already ended)."""
        if self.ended:
            return math.inf
        exit_by = self.state.exit_by()
        if math.isfinite(exit_by):  # its handler ran: its own bound
            return exit_by
        return self.signalled_at + (self.grace_s or 0.0)

    def why(self, now: float) -> str:
        if math.isfinite(self.state.exit_by()):
            if not self.signal_name:
                return "the car did not end by the bound its own stop set"
            return f"the car did not end within {now - self.signalled_at:.1f} s of {self.signal_name} (its own bound)"
        return (
            f"the car did not exit within {now - self.signalled_at:.1f} s of {self.signal_name} "
            "(its signal handler never ran: C code holding the GIL?)"
        )


def _car_gone(car_pid: int) -> bool:
    return os.getppid() != car_pid


def _open_watch(config: dict[str, Any], car_pid: int) -> tuple[list[int], int | None]:
    """The descriptors to wait on: stdin (the car's command pipe), the car's pidfd, the signal wakeup pipe."""
    watch = [sys.stdin.fileno()]
    if hasattr(os, "pidfd_open"):
        try:
            watch.append(os.pidfd_open(car_pid))
        except OSError:
            pass
    sig_fd = config.get("signal_fd")
    if isinstance(sig_fd, int) and sig_fd >= 0:
        os.set_blocking(sig_fd, False)
        watch.append(sig_fd)
        return watch, sig_fd
    return watch, None


def _end_car(guard: Guard, car_pid: int, why: str) -> None:
    """The car would not end: every safe state first, one line saying why, then SIGKILL."""
    guard.all_safe(STOP_RETRY_S, why)
    guard.log("kill", f"{why}: killing it (SIGKILL, pid {car_pid})", 0)
    try:
        os.kill(car_pid, signal.SIGKILL)
    except OSError as exc:
        guard.log("kill-failed", f"could not kill the car (pid {car_pid}): {exc}", 0)


def main() -> int:
    """Read the configuration line, open every output, say ``ready``, then guard until the car stops or dies."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the car's to handle; the guard ends with it
    stopping: list[str] = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append("SIGTERM"))
    config = json.loads(sys.stdin.buffer.readline())
    car_pid = int(config["car_pid"])
    try:
        outputs = [Output(r) for r in config["routes"]]
        state = SharedState.attach(int(config["fd"]), len(outputs))
    except Exception as exc:
        print(f"error {type(exc).__name__}: {exc}", flush=True)
        return 2
    try:  # a guard that waits behind the car's busy threads for a CPU would defeat itself
        os.setpriority(os.PRIO_PROCESS, 0, -10)
    except OSError:
        pass
    first = tuple(int(i) for i in config.get("first", ()))
    guard = Guard(state, outputs, float(config["heartbeat_timeout_s"]), first)
    grace = config.get("exit_grace_s")
    exits = ExitWatch(state, None if grace is None else float(grace))
    watch, sig_fd = _open_watch(config, car_pid)
    state.set_guard_beat(time.monotonic())
    print("ready", flush=True)
    reason = ""
    while not reason:
        now = time.monotonic()
        wake = guard.step(now)
        if stopping:
            reason = stopping[0]
            break
        if now >= exits.due():
            _end_car(guard, car_pid, exits.why(now))
            exits.ended = True  # once; the car's pidfd says when it is gone
        wake = min(wake, exits.due())
        ready, _, _ = select.select(watch, [], [], max(0.0, wake - time.monotonic()))
        for fd in ready:
            if fd == watch[0]:
                line = sys.stdin.buffer.readline()
                reason = "stop" if line.strip() == b"stop" else "car gone (its pipe closed)"
            elif fd == sig_fd:
                try:
                    data = os.read(fd, 64)
                except BlockingIOError:
                    continue
                if data:
                    exits.signalled(data, time.monotonic())
                else:
                    watch.remove(fd)  # every writer closed it: the car is going; the pidfd tells when
            else:
                reason = "car gone (its process ended)"
        if not reason and _car_gone(car_pid):
            reason = "car gone (reparented)"
    orphaned = reason != "stop"
    guard.all_safe(ORPHAN_RETRY_S if orphaned else STOP_RETRY_S, reason, quiet=not orphaned)
    if not orphaned:
        print(json.dumps({"slots": [state.guard_stats(i) for i in range(len(outputs))]}), flush=True)
    for o in outputs:
        o.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
