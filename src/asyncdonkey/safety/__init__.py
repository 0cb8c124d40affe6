"""Safety: what puts the car's actuators in their safe state whatever the car's own process does.

What lives here:

* :mod:`asyncdonkey.safety.watchdog` — the in-process watchdog, the fast first line: a thread beside the loop
  that writes an actuator's safe state when its command deadline passes, even while a sync part holds the loop
  thread;
* :mod:`asyncdonkey.safety.guard` — the safety process: a separate interpreter with its own handle on each
  actuator's bus, watching command deadlines, the drive's heartbeat and the car process's life (it runs as
  ``python -I guard.py``, so it imports nothing but the standard library and smbus2);
* :mod:`asyncdonkey.safety.process` — the car's side of it (start, heartbeat, deadlines, figures);
* :mod:`asyncdonkey.safety.unsafe` — how long an output was unsafe, measured from the deadline that made it so;
* :mod:`asyncdonkey.safety.activity` — what the loop thread is doing, as the watchdog and the signal handler
  read it (Protocols the core's ``Drive`` satisfies);
* :mod:`asyncdonkey.safety.attach` — one drive's safety attachment: it starts the safety process and the
  watchdog and wires each actuator to them, called by the drive (typed against
  :class:`~asyncdonkey.safety.attach.SafetyHost`, never the ``Drive`` class).

The rest of the safety story sits where its work is: :mod:`asyncdonkey.core.signals` (Ctrl-C and SIGTERM stop the
drive within a bound, a second one makes the actuators safe and exits), the first phase of
:mod:`asyncdonkey.core.shutdown` (every actuator's safe state before any other part shuts down),
:mod:`asyncdonkey.parts.failsafe` (a stale-command stop for actuators without one of their own) and the
actuators themselves (:mod:`asyncdonkey.parts.actuators`: ``PWMThrottle``'s stale-command failsafe and the
``safe_state_sync`` path every safe-state write takes). ``docs/safety.md`` lists every fault, the response, its
bound and its test, and which faults only the safety process catches.

This package's ``__init__`` imports only :mod:`.process` and :mod:`.unsafe` (neither imports the core), so
importing :mod:`asyncdonkey.safety.watchdog` from the drive loop adds no import cycle.
"""

from .process import GuardedOutput, SafetyProcess, SafetyProcessError
from .unsafe import UnsafeTime

__all__ = ["GuardedOutput", "SafetyProcess", "SafetyProcessError", "UnsafeTime"]
