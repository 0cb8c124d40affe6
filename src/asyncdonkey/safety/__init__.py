"""Safety: what puts the car's actuators in their safe state whatever the car's own process does.

* :mod:`asyncdonkey.safety.guard` — the safety process: a separate interpreter with its own handle on each
  actuator's bus, watching command deadlines, the drive's heartbeat and the car process's life;
* :mod:`asyncdonkey.safety.process` — the car's side of it (start, heartbeat, deadlines, figures);
* :mod:`asyncdonkey.safety.unsafe` — how long an output was unsafe, measured from the deadline that made it so.

The in-process watchdog thread (:mod:`asyncdonkey.watchdog`) stays the fast first line. ``docs/safety.md``
lists every fault, the response, its bound and its test, and which faults only the safety process catches.
"""

from .process import GuardedOutput, SafetyProcess, SafetyProcessError
from .unsafe import UnsafeTime

__all__ = ["GuardedOutput", "SafetyProcess", "SafetyProcessError", "UnsafeTime"]
