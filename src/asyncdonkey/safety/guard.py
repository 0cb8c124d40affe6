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
(a NACK, a bus error) is retried with a bounded backoff until it lands, each attempt counted.

It imports only the standard library and smbus2 (a test's served I2C simulator is imported only when a route
names one), so it starts in tens of milliseconds and holds a few MB. It is started as a script by path
(``python -I guard.py``) with the car's shared state passed as an inherited memory file descriptor; the same
file is also the ``asyncdonkey.safety.guard`` module, which the car imports for the shared layout.

The shared state is a small memory-mapped file: a header (the heartbeat and the drive's phase, and the total
of the guard's safe writes, which the car checks once a tick to rewrite its outputs after the guard touched
them) and one slot per actuator (the command deadline and a command count from the car; the guard's counts,
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
VERSION = 1
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
# slot fields (offsets within a slot)
_S_DEADLINE = 0  # f64, car: when the current command goes stale (inf: no failsafe)
_S_SEQ = 8  # u64, car: commands applied
_S_WRITES = 16  # u64, guard: safe writes landed
_S_FAILED = 24  # u64, guard: safe-write attempts that failed
_S_EVENTS = 32  # u64, guard: times tripped
_S_UNSAFE_TOTAL = 40  # f64, guard: seconds from the trip's cause to its safe write landing, summed
_S_UNSAFE_MAX = 48  # f64, guard
_S_LAST_CAUSE = 56  # f64, guard: the deadline (or heartbeat timeout) of the latest trip
_S_LAST_LANDED = 64  # f64, guard: when its safe write landed (nan until it has)

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
        for i in range(slots):
            state._set_d(i, _S_DEADLINE, math.inf)
            state._set_d(i, _S_LAST_CAUSE, math.nan)
            state._set_d(i, _S_LAST_LANDED, math.nan)
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
        """``(cause, landed)`` of the guard's latest trip of this slot (nan where there is none yet)."""
        return self._get_d(slot, _S_LAST_CAUSE), self._get_d(slot, _S_LAST_LANDED)


# ------------------------------------------------------------------------------------- the outputs


class Output:
    """One actuator's output as the guard reaches it: a register block on an I2C chip, through its own handle."""

    def __init__(self, route: dict[str, Any]) -> None:
        self.name = str(route.get("name", "output"))
        self.address = int(route["address"])
        self.register = int(route["register"])
        self.data = [int(b) for b in route["data"]]
        ai = route.get("auto_increment")
        self.ai_register, self.ai_mask = (int(ai[0]), int(ai[1])) if ai else (None, 0)
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

#: the longest the guard sleeps: a deadline can move earlier without telling it (a command with an older origin)
POLL_S = 0.02
#: how often a tripped output is read back, to catch a stale write from the car that landed after the safe one
VERIFY_S = 0.1
#: the retry backoff of a failed safe write: first pause, cap
RETRY_FIRST_S = 0.002
RETRY_MAX_S = 0.05
#: after the car is gone: how long to keep retrying a safe write that will not land before giving up
ORPHAN_RETRY_S = 30.0


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


class Guard:
    """The guard's state and decisions; :func:`main` runs it."""

    def __init__(self, state: SharedState, outputs: list[Output], heartbeat_timeout_s: float) -> None:
        self.state = state
        self.slots = [_Slot(o) for o in outputs]
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.writes_total = 0
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
        """Check every slot and act; returns when to look again."""
        wake = now + POLL_S
        st = self.state
        for i, s in enumerate(self.slots):
            cause = self._cause(i, now)
            if cause is None:
                if s.tripped and (st.seq(i) != s.seq_at_trip or st.deadline(i) == math.inf):
                    s.tripped = s.pending = False  # the car is back with a fresh command (or has no deadline)
                    s.next_verify = math.inf
                    continue
                if not s.tripped:
                    deadline = st.deadline(i)
                    if deadline < wake:
                        wake = deadline
                    continue
            elif not s.tripped:
                s.tripped = s.pending = True
                s.cause, s.seq_at_trip, s.failed, s.next_attempt = cause, st.seq(i), 0, now
                st._set_q(i, _S_EVENTS, st._get_q(i, _S_EVENTS) + 1)
                st._set_d(i, _S_LAST_CAUSE, cause)
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
            s.next_attempt = time.monotonic() + min(RETRY_FIRST_S * 2 ** (s.failed - 1), RETRY_MAX_S)
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

    def all_safe(self, give_up_s: float) -> None:
        """The car is gone or done: every output to its safe state, each retried until it lands or ``give_up_s``."""
        until = time.monotonic() + give_up_s
        for i, s in enumerate(self.slots):
            attempt = 0
            while True:
                try:
                    s.out.write_safe()
                    break
                except OSError as exc:
                    attempt += 1
                    self.state._set_q(i, _S_FAILED, self.state._get_q(i, _S_FAILED) + 1)
                    self.log(f"fail{i}", f"{s.out.name}: safe-state write failed (attempt {attempt}): {exc}")
                    if time.monotonic() >= until:
                        self.log(f"gave{i}", f"{s.out.name}: gave up after {attempt} attempts", 0)
                        break
                    time.sleep(min(RETRY_FIRST_S * 2 ** (attempt - 1), RETRY_MAX_S))


def _car_gone(car_pid: int) -> bool:
    return os.getppid() != car_pid


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
    guard = Guard(state, outputs, float(config["heartbeat_timeout_s"]))
    watch = [sys.stdin.fileno()]
    if hasattr(os, "pidfd_open"):
        try:
            watch.append(os.pidfd_open(car_pid))
        except OSError:
            pass
    print("ready", flush=True)
    reason = ""
    while not reason:
        now = time.monotonic()
        wake = guard.step(now)
        if stopping:
            reason = stopping[0]
            break
        ready, _, _ = select.select(watch, [], [], max(0.0, wake - time.monotonic()))
        for fd in ready:
            if fd == watch[0]:
                line = sys.stdin.buffer.readline()
                reason = "stop" if line.strip() == b"stop" else "car gone (its pipe closed)"
            else:
                reason = "car gone (its process ended)"
        if not reason and _car_gone(car_pid):
            reason = "car gone (reparented)"
    orphaned = reason.startswith("car gone") or reason == "SIGTERM"
    guard.all_safe(ORPHAN_RETRY_S if orphaned else 2.0)
    if orphaned:
        guard.log("end", f"{reason}: every output written to its safe state", 0)
    else:
        print(json.dumps({"slots": [state.guard_stats(i) for i in range(len(outputs))]}), flush=True)
    for o in outputs:
        o.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
