"""The fleet view: each car publishes a small status on ``<prefix>/status``; ``asyncdonkey top`` shows them all.

A car adds :class:`FleetStatus` (no outputs; its inputs are the drive mode and the record count)::

    v.add(FleetStatus(link, v, ages=["cam/image_array", "pilot/throttle"]), inputs=["user/mode", "tub/num_records"])

Every ``every_s`` its background task publishes one JSON document (encoding ``application/json``) on
``<prefix>/status``, readable by any Zenoh client::

    {"car": "cars/car1", "hz": 20.0, "lateness_p99_ms": 0.41, "overruns": 0, "ticks": 1200,
     "parts": {"SimCamera": 0.05, ...}, "ages_ms": {"cam/image_array": 12.3, ...},
     "latency_p50_ms": 11.2, "latency_p99_ms": 17.0,
     "mode": "local", "records": 0, "rtt_ms": 0.3, "sent_unix": 1767000000.0}

(``parts``: mean ms per part over the last ``window`` ticks; ``ages_ms``: age of each listed channel's value
when the status was made, ``null`` when it holds no value (never written, or ``None``: a remote pilot's
subscriber writes ``None`` until the first command arrives); ``overruns``: ticks over their period in that window;
``latency_*``: the sensing-to-actuation latency of the car's first actuator over that window, ``null``
without one.)

``asyncdonkey top`` subscribes to ``cars/*/status`` and redraws one row per car, htop-style, sorted by name,
latency or age (``--sort``). Each row's state says what to look at first: ``live``; ``STALE`` when one of the
car's listed ages is past the stale limit (``--stale-ms``, default 250, the cars' failsafe window: that car is
probably holding its failsafe); ``NO-CMD`` when the car has no command (below); ``SILENT`` when its
status has not come for three periods (the car, its link or its process is gone). Precedence: ``SILENT``, then
``NO-CMD``, then ``STALE``.

**No command** is read from the ages the car lists: its *command channels* are the listed ones under
``pilot/`` (``pilot/angle``, ``pilot/throttle``: what a pilot, remote or on a server, writes). When the car lists
at least one and every one is ``null`` (no value), no command has reached it yet (a remote pilot's subscriber
holds its last command once it has one, so a car commanded once shows ``STALE`` when the commands stop, not
this): it stands still on its own failsafe, and the usual causes are that it is not among the server's
``--cars``, is paired with another CA, or cannot reach the server. A car that lists no command channel cannot
be judged: it shows ``live`` (or ``STALE``) as before.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TextIO

import numpy as np

from ...clock import get_clock
from ...extras import require
from ...periodic import Periodic
from .link import ZenohLink, zenoh_config

__all__ = [
    "COMMAND_PREFIX",
    "SORT_KEYS",
    "STATES",
    "STATUS_KEY",
    "FleetStatus",
    "FleetWatcher",
    "car_state",
    "never_commanded",
    "render_fleet",
    "top_main",
]

STATUS_KEY = "status"
#: the listed ages whose channel starts with this are the car's command channels (module docstring)
COMMAND_PREFIX = "pilot/"
#: ``top``'s states, and the words its summary line counts them by
STATES = {"live": "live", "NO-CMD": "no command", "STALE": "stale", "SILENT": "silent"}


class FleetStatus:
    """Publish the car's status on ``<prefix>/status`` every ``every_s`` (see the module docstring)."""

    def __init__(
        self,
        link: ZenohLink,
        vehicle: Any,
        *,
        ages: Sequence[str] = (),
        every_s: float = 0.5,
        window: int = 200,
    ) -> None:
        if not every_s > 0:
            raise ValueError(f"FleetStatus: every_s must be > 0, got {every_s!r}")
        self.link = link.acquire()
        self.vehicle = vehicle
        self.ages = tuple(ages)
        self.every_s = float(every_s)
        self.window = int(window)
        self.ticks = 0
        self.mode: Any = None
        self.records: Any = None
        self._pub = link.session.declare_publisher(link.key(STATUS_KEY))
        self.published = 0

    def run(self, mode: Any = None, records: Any = None) -> None:
        self.ticks += 1
        self.mode = mode
        self.records = records

    def status(self, hz: float) -> dict[str, Any]:
        prof = self.vehicle.profiler
        w = self.window
        late = prof.lateness.recent(drop_last=False)[-w:]
        over = prof.overrun.recent(drop_last=False)[-w:]
        parts = {}
        for name, series in prof.parts.items():
            recent = series.recent(drop_last=False)[-w:]
            if len(recent):
                parts[name] = round(float(recent.mean()) * 1e3, 3)
        mem = self.vehicle.mem
        ages = {}
        for ch in self.ages:
            a = mem.age(ch)
            # no value, no age: a remote command's subscriber writes None, freshly dated, until its first sample
            has_value = ch in mem and mem[ch] is not None
            ages[ch] = round(a * 1e3, 1) if has_value and math.isfinite(a) else None
        rtt = self.link.rtt_s()
        latency: Any = next(iter(prof.latency.values()), None)
        lat = latency.recent(drop_last=False)[-w:] if latency is not None else ()
        return {
            "car": self.link.prefix,
            "hz": round(hz, 2),
            "lateness_p99_ms": round(float(np.percentile(late, 99)) * 1e3, 3) if len(late) else None,
            "overruns": int(np.count_nonzero(over > 0)) if len(over) else 0,
            "ticks": self.ticks,
            "parts": parts,
            "ages_ms": ages,
            "latency_p50_ms": round(float(np.percentile(lat, 50)) * 1e3, 2) if len(lat) else None,
            "latency_p99_ms": round(float(np.percentile(lat, 99)) * 1e3, 2) if len(lat) else None,
            "mode": None if self.mode is None else str(self.mode),
            "records": self.records if isinstance(self.records, int | float) else None,
            "rtt_ms": round(rtt[1] * 1e3, 3) if rtt else None,
            "sent_unix": time.time(),  # for humans only; ages above never depend on it
        }

    def publish(self, hz: float) -> dict[str, Any]:
        doc = self.status(hz)
        self._pub.put(json.dumps(doc, separators=(",", ":")).encode(), encoding="application/json")
        self.published += 1
        return doc

    async def update(self) -> None:
        clock = get_clock()
        t_last, n_last = clock.now(), self.ticks
        with Periodic(self.every_s) as every:
            while not self.link.closed:
                await every.next()
                now, n = clock.now(), self.ticks
                hz = (n - n_last) / (now - t_last) if now > t_last else 0.0
                t_last, n_last = now, n
                self.publish(hz)

    def shutdown(self) -> None:
        try:
            self._pub.undeclare()
        except Exception:
            pass
        self.link.release()


class FleetWatcher:
    """Collect the newest status of every car matching ``key`` (``cars/*/status``) on a Zenoh session."""

    def __init__(self, session: Any, key: str = f"cars/*/{STATUS_KEY}") -> None:
        self._lock = threading.Lock()
        self.cars: dict[str, tuple[dict[str, Any], float]] = {}
        self.bad = 0
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            doc = json.loads(sample.payload.to_bytes())
            if not isinstance(doc, dict):
                raise ValueError("not an object")
        except ValueError:
            with self._lock:
                self.bad += 1
            return
        key = str(sample.key_expr)
        name = key[: -len(STATUS_KEY) - 1] if key.endswith("/" + STATUS_KEY) else key
        with self._lock:
            self.cars[name] = (doc, time.monotonic())

    def snapshot(self) -> dict[str, tuple[dict[str, Any], float]]:
        with self._lock:
            return dict(self.cars)

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass


def _ms(x: Any, fmt: str = "{:.2f}") -> str:
    return "-" if x is None else fmt.format(x)


#: what ``top --sort`` orders the cars by
SORT_KEYS = ("name", "latency", "age")


def never_commanded(doc: Mapping[str, Any]) -> bool:
    """Whether the status says no command has reached the car: it lists ages of command channels
    (:data:`COMMAND_PREFIX`) and every one is ``null`` (no value). ``False`` when it lists none (nothing to judge
    by)."""
    ages = doc.get("ages_ms")
    if not isinstance(ages, Mapping):
        return False
    commands = [v for k, v in ages.items() if isinstance(k, str) and k.startswith(COMMAND_PREFIX)]
    return bool(commands) and all(v is None for v in commands)


def car_state(doc: Mapping[str, Any], seen_s: float, *, gone_after_s: float = 3.0, stale_ms: float = 250.0) -> str:
    """``"SILENT"`` (no status for ``gone_after_s``), ``"NO-CMD"`` (no command yet: :func:`never_commanded`),
    ``"STALE"`` (an age past ``stale_ms``) or ``"live"``."""
    if seen_s > gone_after_s:
        return "SILENT"
    if never_commanded(doc):
        return "NO-CMD"
    ages = doc.get("ages_ms") or {}
    if any(isinstance(v, int | float) and v > stale_ms for v in ages.values()):
        return "STALE"
    return "live"


def _oldest_age(doc: Mapping[str, Any]) -> float:
    ages = [v for v in (doc.get("ages_ms") or {}).values() if isinstance(v, int | float)]
    return max(ages) if ages else math.inf


def _order(cars: Mapping[str, tuple[Mapping[str, Any], float]], sort: str) -> list[str]:
    if sort not in SORT_KEYS:
        raise ValueError(f"top: --sort must be one of {', '.join(SORT_KEYS)}, got {sort!r}")
    if sort == "name":
        return sorted(cars)

    def key(name: str) -> tuple[float, str]:
        doc = cars[name][0]
        if sort == "latency":
            lat = doc.get("latency_p99_ms")
            return (-lat if isinstance(lat, int | float) else math.inf, name)  # slowest first, unknown last
        return (-_oldest_age(doc) if math.isfinite(_oldest_age(doc)) else math.inf, name)

    return sorted(cars, key=key)


def render_fleet(
    cars: Mapping[str, tuple[Mapping[str, Any], float]],
    now: float,
    *,
    gone_after_s: float = 3.0,
    width: int | None = None,
    sort: str = "name",
    stale_ms: float = 250.0,
    parts: bool = True,
) -> str:
    """The ``top`` screen as text: a header, one row per car (ordered by ``sort``: ``name``, ``latency``
    slowest first, ``age`` oldest first) and, with ``parts``, its part times beneath. Rows are cut at ``width``
    columns (a terminal's width; ``None``: never, for a file or a pipe, which lose nothing by a long line)."""
    states = {
        name: car_state(doc, now - t, gone_after_s=gone_after_s, stale_ms=stale_ms) for name, (doc, t) in cars.items()
    }
    counts = ", ".join(f"{sum(1 for v in states.values() if v == s)} {word}" for s, word in STATES.items())
    lines = [f"asyncdonkey top - {len(cars)} car{'s' if len(cars) != 1 else ''} seen, {counts} (sorted by {sort})"]
    head = (
        f"{'CAR':<16} {'STATE':<6} {'HZ':>6} {'LAT p99':>8} {'LATE p99':>9} {'OVR':>4} {'MODE':<11} {'REC':>6}"
        f" {'RTT ms':>7} {'SEEN':>5}  AGES ms"
    )
    lines.append(head)
    for name in _order(cars, sort):
        doc, t = cars[name]
        seen = now - t
        ages = doc.get("ages_ms") or {}
        age_text = " ".join(f"{k}={_ms(v, '{:.0f}')}" for k, v in ages.items())
        row = (
            f"{name[-16:]:<16} {states[name]:<6} {_ms(doc.get('hz'), '{:6.1f}'):>6}"
            f" {_ms(doc.get('latency_p99_ms'), '{:.1f}'):>8} {_ms(doc.get('lateness_p99_ms')):>9}"
            f" {doc.get('overruns', 0):>4} {str(doc.get('mode') or '-')[:11]:<11}"
            f" {_ms(doc.get('records'), '{:.0f}'):>6}"
            f" {_ms(doc.get('rtt_ms')):>7} {min(seen, 999.9):4.1f}s  {age_text}"
        )
        lines.append(row[:width] if width is not None else row)
        part_times = doc.get("parts") or {}
        if parts and part_times:
            slow = sorted(part_times.items(), key=lambda kv: -kv[1])
            text = "  ".join(f"{k} {v:.2f}" for k, v in slow)
            line = "    parts ms: " + text
            lines.append(line[:width] if width is not None else line)
    if not cars:
        lines.append("(no car status yet: is a car publishing on this network, and are we connected to it?)")
    return "\n".join(lines)


def screen_width(out: TextIO) -> int | None:
    """The columns ``top`` may fill on ``out``: the terminal's width when ``out`` is a terminal (read on every
    redraw, so a resized window is followed), ``None`` (no limit) when it is a file or a pipe."""
    if not out.isatty():
        return None
    try:
        return os.get_terminal_size(out.fileno()).columns
    except (OSError, ValueError, io.UnsupportedOperation):  # a terminal-like stream without a size
        return shutil.get_terminal_size((120, 24)).columns


def top_main(args: Any, *, stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic) -> int:
    """``asyncdonkey top``: redraw every ``--every`` seconds until Ctrl-C, or print once after ``--once`` s."""
    zenoh = require("zenoh", "zenoh", "asyncdonkey top")

    out = stream or sys.stdout
    cfg = zenoh_config(
        args.config,
        mode=args.mode,
        connect=args.connect,
        listen=args.listen,
        # a config file decides; named endpoints need no discovery; neither: find the cars on the LAN
        multicast_scouting=None if args.config else not (args.connect or args.listen),
    )
    session = zenoh.open(cfg)
    watcher = FleetWatcher(session, args.key)
    tty = out.isatty()
    try:
        view: dict[str, Any] = {
            "sort": getattr(args, "sort", "name"),
            "stale_ms": getattr(args, "stale_ms", 250.0),
            "parts": not getattr(args, "no_parts", False),
        }
        if args.once is not None:
            time.sleep(args.once)
            out.write(render_fleet(watcher.snapshot(), clock(), width=screen_width(out), **view) + "\n")
            return 0
        while True:
            screen = render_fleet(
                watcher.snapshot(), clock(), gone_after_s=3 * max(args.every, 0.5), width=screen_width(out), **view
            )
            out.write(("\x1b[H\x1b[2J" if tty else "") + screen + "\n")
            out.flush()
            time.sleep(args.every)
    except KeyboardInterrupt:
        return 0
    finally:
        watcher.close()
        session.close()
