"""The Foxglove layout for a car: camera with steering, user-vs-pilot plots, the loop's timing, the GPS track.

The file is in the form the Foxglove app exports and reads back with *Layouts* → *Import from file…*::

    {"configById": {"Plot!steering": {...panel config...}, ...},
     "globalVariables": {}, "userNodes": {}, "playbackConfig": {"speed": 1},
     "layout": {"first": "Image!camera", "second": {...}, "direction": "row", "splitPercentage": 50}}

``layout`` is the panels' arrangement (a binary tree of splits whose leaves are panel ids), ``configById`` each
panel's settings keyed by ``"<panel type>!<id>"``; a panel's title is its config's ``foxglovePanelTitle``.
(foxglove-sdk's ``foxglove.layouts`` writes another form, ``{"version": 1, "content": ...}``; the files the app
exports, which are what its import is documented to read, are in this one.)

A panel is only shown when the car has its channels: no map without ``gps/latitude`` and ``gps/longitude``, no
pilot series without ``pilot/angle``, and so on (:func:`build_layout` with ``channels=``, or
:func:`layout_for_vehicle` to take them from a Vehicle's parts), because a panel whose topic never comes shows
only "waiting for data".

``layout.json`` beside this module is :func:`build_layout` for a Donkeycar car without GPS
(:data:`DONKEYCAR_CHANNELS`: camera, user and pilot commands, drive mode, with actuators; a test keeps the two
equal). ``python -m asyncdonkey.parts.mcap.layout`` prints its path; ``--print`` prints a layout, ``--write
[PATH]`` writes one (the shipped file by default); ``--channels ...``, ``--gps`` and ``--image-topic`` build one
for another car.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from .encode import LATENCY_TOPIC, PARTS_TOPIC, TICK_TOPIC, topic_for

__all__ = [
    "DONKEYCAR_CHANNELS",
    "GPS_CHANNELS",
    "PANEL_TYPES",
    "build_layout",
    "layout_data",
    "layout_for_vehicle",
    "layout_path",
    "vehicle_channels",
]

DONKEYCAR_CHANNELS: tuple[str, ...] = (
    "cam/image_array",
    "user/angle",
    "user/throttle",
    "user/mode",
    "pilot/angle",
    "pilot/throttle",
)
"""The channels of a Donkeycar car (camera, web or joystick controller, pilot, drive mode): the shipped layout's."""
GPS_CHANNELS: tuple[str, str] = ("gps/latitude", "gps/longitude")
"""The recorder turns these two into ``/gps/fix`` (``foxglove.LocationFix``), which the Map panel follows."""
STEERING_CHANNELS: tuple[str, str] = ("user/angle", "pilot/angle")
"""The angles the recorder draws over each camera frame (``<image topic>/steering``), by default."""
PANEL_TYPES = frozenset({"Image", "Plot", "RawMessages", "Map"})
"""The Foxglove panel types this module writes."""

USER_COLOR, PILOT_COLOR = "#22c55e", "#d946ef"  # green and magenta, as the steering overlay draws them


def layout_path() -> Path:
    """The shipped layout file."""
    return Path(__file__).with_name("layout.json")


def vehicle_channels(vehicle: Any) -> set[str]:
    """Every channel some part of ``vehicle`` writes: what a recording of it can contain."""
    return {ch for entry in vehicle.parts for ch in entry.outputs}


def layout_for_vehicle(vehicle: Any, **kw: Any) -> str:
    """The layout for ``vehicle``: panels for the channels its parts write, the latency panel if it has an
    actuator (the loop measures sensing-to-actuation latency only for actuators). ``kw`` as
    :func:`build_layout`."""
    kw.setdefault("actuators", any(entry.actuator for entry in vehicle.parts))
    return build_layout(vehicle_channels(vehicle), **kw)


def build_layout(channels: Iterable[str] = DONKEYCAR_CHANNELS, **kw: Any) -> str:
    """The layout as the JSON text Foxglove imports. Arguments as :func:`layout_data`."""
    return json.dumps(layout_data(channels, **kw), indent=1)


def layout_data(
    channels: Iterable[str] = DONKEYCAR_CHANNELS,
    *,
    image: str = "cam/image_array",
    user: str = "user",
    pilot: str = "pilot",
    mode: str = "user/mode",
    gps: tuple[str, str] = GPS_CHANNELS,
    timing: bool = True,
    actuators: bool = True,
) -> dict[str, Any]:
    """The layout (Foxglove's ``LayoutData``) for a car that writes ``channels``.

    Args:
        channels: the Memory channels the car writes (:func:`vehicle_channels`); panels and plot series whose
            channels are absent are left out.
        image: the camera channel; user, pilot: the prefixes of the ``angle`` and ``throttle`` channels;
            mode: the drive mode channel; gps: the latitude and longitude channels.
        timing: the recorder records the loop's timing (``timing=True``, its default): the tick timing plot
            and the part times.
        actuators: the car has actuators, so ``/asyncdonkey/latency`` is recorded.
    """
    has = set(channels)
    # (share of the width, [(panel id, share of the column's height, config or None when not shown)])
    columns = (
        (
            3,
            [
                ("Image!camera", 2, _camera(has, image)),
                ("Plot!steering", 1, _versus(has, "angle", user, pilot)),
                ("Plot!throttle", 1, _versus(has, "throttle", user, pilot)),
            ],
        ),
        (
            2,
            [
                ("Plot!timing", 1, _timing_plot() if timing else None),
                ("RawMessages!parts", 1, _raw("part times (ms)", PARTS_TOPIC) if timing else None),
                (
                    "RawMessages!latency",
                    1,
                    _raw("sensing-to-actuation latency (ms)", LATENCY_TOPIC) if timing and actuators else None,
                ),
            ],
        ),
        (
            1,
            [
                ("RawMessages!mode", 1, _raw("drive mode", f"{topic_for(mode)}.value") if mode in has else None),
                ("Map!gps", 1, _map() if all(ch in has for ch in gps) else None),
            ],
        ),
    )
    panels = {pid: config for _, column in columns for pid, _, config in column if config is not None}
    row = [
        (share, _split("column", [(h, pid) for pid, h, config in column if config is not None]))
        for share, column in columns
    ]
    return {
        "configById": panels,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": _split("row", [(share, node) for share, node in row if node is not None]),
    }


# ------------------------------------------------------------------------------------------------- panels
def _camera(has: set[str], image: str) -> dict[str, Any] | None:
    """The camera, with the steering overlay when the recorder draws one (it needs an angle channel)."""
    if image not in has:
        return None
    topic = topic_for(image)
    overlay = any(ch in has for ch in STEERING_CHANNELS)
    return {
        "foxglovePanelTitle": "camera",
        "imageMode": {
            "imageTopic": topic,
            "annotations": {f"{topic}/steering": {"visible": True}} if overlay else {},
        },
    }


def _versus(has: set[str], what: str, user: str, pilot: str) -> dict[str, Any] | None:
    """``angle`` or ``throttle``: the user's and the pilot's command on one plot, those the car has."""
    series = [
        _series(f"{topic_for(f'{who}/{what}')}.value", label, color)
        for who, label, color in ((user, "user", USER_COLOR), (pilot, "pilot", PILOT_COLOR))
        if f"{who}/{what}" in has
    ]
    title = f"{'steering' if what == 'angle' else what}: " + " vs ".join(s["label"] for s in series)
    return _plot(title, series, minYValue=-1, maxYValue=1) if series else None


def _timing_plot() -> dict[str, Any]:
    return _plot(
        "tick timing (ms)",
        [
            _series(f"{TICK_TOPIC}.lateness_ms", "lateness", "#f97316"),
            _series(f"{TICK_TOPIC}.duration_ms", "duration", "#3b82f6"),
            _series(f"{TICK_TOPIC}.overrun_ms", "overrun", "#ef4444"),
        ],
    )


def _plot(title: str, series: list[dict[str, Any]], **axes: float) -> dict[str, Any]:
    return {
        "foxglovePanelTitle": title,
        "paths": series,
        **axes,
        "showLegend": True,
        "legendDisplay": "top",
        "xAxisVal": "timestamp",
    }


def _series(path: str, label: str, color: str) -> dict[str, Any]:
    # receiveTime: the messages are JSON without a header stamp; their log time is when the tick recorded them
    return {"value": path, "enabled": True, "timestampMethod": "receiveTime", "label": label, "color": color}


def _raw(title: str, topic_path: str) -> dict[str, Any]:
    return {"foxglovePanelTitle": title, "topicPath": topic_path}


def _map() -> dict[str, Any]:
    return {"foxglovePanelTitle": "GPS", "followTopic": "/gps/fix"}


def _split(direction: str, items: list[tuple[float, Any]]) -> Any:
    """Items side by side (``row``) or stacked (``column``), sized by their proportions, as nested two-way splits:
    the first item against the rest, which split again."""
    if not items:
        return None
    if len(items) == 1:
        return items[0][1]
    (share, first), rest = items[0], items[1:]
    total = share + sum(p for p, _ in rest)
    return {
        "first": first,
        "second": _split(direction, rest),
        "direction": direction,
        "splitPercentage": round(100 * share / total, 2),
    }


# ------------------------------------------------------------------------------------------------- command line
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="Print or build the Foxglove layout for an asyncdonkey car.")
    ap.add_argument("--print", action="store_true", help="print the layout JSON instead of its path")
    ap.add_argument(
        "--write",
        nargs="?",
        const=layout_path(),
        type=Path,
        metavar="PATH",
        help="write the layout (to the shipped layout.json when no PATH is given)",
    )
    ap.add_argument(
        "--channels",
        nargs="+",
        metavar="CHANNEL",
        help=f"the channels the car writes (default: a Donkeycar car, {' '.join(DONKEYCAR_CHANNELS)})",
    )
    ap.add_argument("--gps", action="store_true", help=f"the car has GPS ({' and '.join(GPS_CHANNELS)})")
    ap.add_argument("--image-topic", default="/cam/image_array", help="the camera's topic")
    ap.add_argument("--no-actuators", action="store_true", help="the car has no actuators: no latency panel")
    args = ap.parse_args(argv)
    image = args.image_topic.lstrip("/")
    channels = set(args.channels or DONKEYCAR_CHANNELS)
    if args.channels is None and image != "cam/image_array":
        channels = (channels - {"cam/image_array"}) | {image}
    if args.gps:
        channels |= set(GPS_CHANNELS)
    text = build_layout(channels, image=image, actuators=not args.no_actuators)
    if args.write is not None:
        args.write.write_text(text + "\n")
    if args.print:
        print(text)
    elif args.write is None:
        print(layout_path())


if __name__ == "__main__":
    main()
