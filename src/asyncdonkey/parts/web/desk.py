"""One driver at a time: who holds the controls (what a command may contain is :mod:`.intake`'s).

With Donkeycar's web controller every open page sends its joystick, so two phones fight over the car and the
one whose stick is at rest keeps sending zeros. Here the car has one *driver* at a time; every other page
watches (video, mode, record count, health) and its drive commands are ignored. The rules:

* **Taking control**: a client's drive command takes control when nobody holds it, or when the holder has sent
  nothing for ``idle_release_s`` (it went quiet: a frozen page, a dead link).
* **Keeping it**: the driver's page sends its command at a steady rate while it drives, so it keeps control
  (and keeps its command fresh for the throttle's stale-command failsafe).
* **Releasing it**: the driver closes the page, its page goes hidden (it sends ``{"release": true}``), its
  connection drops, or it goes quiet for ``idle_release_s``.
* **Stop is for everyone**: ``{"stop": true}`` from any client stops the car (throttle 0, mode ``user``) and
  hands control to that client, so a watcher can always stop a car someone else drives.
* **Who is a client**: a WebSocket is one; a ``POST /drive`` script is its *session*, a cookie the server sets
  (never its address: two scripts on one machine are two clients). A script that does not return the cookie
  has no session and never holds control: each of its commands applies only while nobody holds it (as with
  Donkeycar, where every ``POST`` drives), and its stop frees control rather than holding it.
* **Who calibrates** (:meth:`Desk.why_not_calibrator`): the driver; or, while nobody holds control, the client
  that held it last and let it lapse by going quiet (nobody took it since), or the only page open. Control that
  is free because its holder left (a watcher that pressed STOP and closed its page) is nobody's to calibrate
  with while other pages are open: such a client takes control first, with a stopped drive command.
"""

from __future__ import annotations

import math

from .auth import WebConfigError
from .intake import Command, CommandError, parse_command

__all__ = ["Command", "CommandError", "Desk", "parse_command"]


class Desk:
    """Who drives. Clients are identified by any hashable id (a WebSocket, ``"session:<id>"`` for ``POST``).

    Args:
        idle_release_s: a driver that sends nothing for this long loses control to the next client that drives.
    """

    def __init__(self, idle_release_s: float = 1.0) -> None:
        if not (idle_release_s > 0 and math.isfinite(idle_release_s)):
            raise WebConfigError(f"WebController: idle_release_s must be a positive number, got {idle_release_s!r}")
        self.idle_release_s = float(idle_release_s)
        self.driver: object | None = None
        self.last_heard = -math.inf  # runtime-clock time of the driver's latest message
        self.refused = 0  # drive commands ignored because another client drives
        self.handovers = 0
        #: the pages (WebSockets) open now: while control is free, a lone page may calibrate, one among others not
        self.pages: set[object] = set()
        #: the latest driver whose control lapsed by going quiet (not released), until anyone else claims it
        self._lapsed: object | None = None

    def is_free(self, now: float) -> bool:
        return self.driver is None or now - self.last_heard >= self.idle_release_s

    def claim(self, client: object, now: float, *, force: bool = False) -> bool:
        """Give ``client`` control if it holds it, nobody does, the holder went quiet, or ``force`` (stop)."""
        if client is not self.driver and client != self.driver:
            if not (force or self.is_free(now)):
                self.refused += 1
                return False
            self.driver = client
            self.handovers += 1
            self._lapsed = None
        self.last_heard = now
        return True

    def release(self, client: object) -> bool:
        """``client`` gives up control (if it held it). True when it did."""
        if self._lapsed is not None and (client is self._lapsed or client == self._lapsed):
            self._lapsed = None
        if self.driver is not None and (client is self.driver or client == self.driver):
            self.driver = None
            return True
        return False

    def free(self) -> bool:
        """Take control from whoever holds it (a stop from a client without a session). True when someone did."""
        if self.driver is None:
            return False
        self.driver = None
        return True

    def expire(self, now: float) -> bool:
        """Release a driver that went quiet; true when one was released."""
        if self.driver is not None and now - self.last_heard >= self.idle_release_s:
            self.driver, self._lapsed = None, self.driver
            return True
        return False

    def opened(self, page: object) -> None:
        """A page (WebSocket) connected: it counts among those that may be watching."""
        self.pages.add(page)

    def closed(self, page: object) -> bool:
        """A page closed: it no longer counts, and gives up control if it held it. True when it did."""
        self.pages.discard(page)
        return self.release(page)

    def why_not_calibrator(self, client: object, now: float) -> str | None:
        """Why ``client`` may not calibrate now (``None``: it may; see the module docstring). A calibration changes
        what every later command does, so it is the driver's alone: never a watcher's, and never a client's that
        found control free because its holder left while others watch."""
        role = self.role(client, now)
        if role == "you":
            return None
        if role == "other":
            return "another client is driving; only the driver can calibrate"
        lapsed = self.driver if self.driver is not None else self._lapsed
        if lapsed is not None and (client is lapsed or client == lapsed):
            return None  # the driver went quiet (a calibration page at rest) and nobody has taken over
        others = len(self.pages - {client})
        if others:
            return (
                f"control is free and {others} other page(s) are open: take control first with a stopped command "
                "(the calibration page's Centre and stop), then calibrate"
            )
        return None

    def role(self, client: object, now: float) -> str:
        """``"you"`` (``client`` drives), ``"other"`` (someone else does) or ``"free"``."""
        if self.driver is None or now - self.last_heard >= self.idle_release_s:
            return "free"
        return "you" if (client is self.driver or client == self.driver) else "other"
