"""The Foxglove layout shipped with the package: camera with steering, user-vs-pilot plots, the loop's timing.

``layout.json`` beside this module is :func:`build_layout` with the default channel names (a test keeps the
two equal). In Foxglove: *Layouts* → *Import from file…* and pick the file :func:`layout_path` names
(``python -m asyncdonkey.parts.mcap.layout`` prints the path; ``--write`` regenerates the file;
``--image-topic`` and friends build one for other channel names).

Panels: the camera (``/cam/image_array`` with ``/cam/image_array/steering`` drawn over it: user green, pilot
magenta), steering and throttle (user vs pilot), the tick's lateness and duration, the drive mode and the
per-part times and actuator latencies as raw messages, and the GPS track on a map.
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["build_layout", "layout_path"]


def layout_path() -> Path:
    """The shipped layout file."""
    return Path(__file__).with_name("layout.json")


def build_layout(
    image_topic: str = "/cam/image_array",
    user: str = "/user",
    pilot: str = "/pilot",
    mode_topic: str = "/user/mode",
) -> str:
    """The layout as Foxglove's JSON (built with ``foxglove.layouts``)."""
    import foxglove.layouts as fl

    def plot(title: str, series: list[tuple[str, str, str]], **kw: object) -> object:
        return fl.PlotPanel(
            title=title,
            config=fl.PlotConfig(
                paths=[fl.PlotSeries(value=v, label=label, color=color) for v, label, color in series],
                show_legend=True,
                legend_display="top",
                **kw,
            ),
        )

    camera = fl.ImagePanel(
        title="camera",
        config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(
                image_topic=image_topic,
                annotations={f"{image_topic}/steering": fl.ImageAnnotationSettings(visible=True)},
            )
        ),
    )
    steering = plot(
        "steering: user vs pilot",
        [(f"{user}/angle.value", "user", "#22c55e"), (f"{pilot}/angle.value", "pilot", "#d946ef")],
        min_y_value=-1,
        max_y_value=1,
    )
    throttle = plot(
        "throttle: user vs pilot",
        [(f"{user}/throttle.value", "user", "#22c55e"), (f"{pilot}/throttle.value", "pilot", "#d946ef")],
        min_y_value=-1,
        max_y_value=1,
    )
    timing = plot(
        "tick timing (ms)",
        [
            ("/asyncdonkey/tick.lateness_ms", "lateness", "#f97316"),
            ("/asyncdonkey/tick.duration_ms", "duration", "#3b82f6"),
            ("/asyncdonkey/tick.overrun_ms", "overrun", "#ef4444"),
        ],
    )
    parts = fl.RawMessagesPanel(title="part times (ms)", config=fl.RawMessagesConfig(topic_path="/asyncdonkey/parts"))
    latency = fl.RawMessagesPanel(
        title="sensing-to-actuation latency (ms)", config=fl.RawMessagesConfig(topic_path="/asyncdonkey/latency")
    )
    mode = fl.RawMessagesPanel(title="drive mode", config=fl.RawMessagesConfig(topic_path=f"{mode_topic}.value"))
    track = fl.MapPanel(title="GPS", config=fl.MapConfig(follow_topic="/gps/fix"))

    def column(*panels: object) -> object:
        return fl.SplitContainer(direction="column", items=[fl.SplitItem(content=p) for p in panels])

    layout = fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=3, content=column(camera, column(steering, throttle))),
                fl.SplitItem(proportion=2, content=column(timing, parts, latency)),
                fl.SplitItem(proportion=1, content=column(mode, track)),
            ],
        )
    )
    return layout.to_json()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="Print or build the Foxglove layout for an asyncdonkey car.")
    ap.add_argument("--write", action="store_true", help="regenerate the shipped layout.json")
    ap.add_argument("--image-topic", default="/cam/image_array")
    ap.add_argument("--print", action="store_true", help="print the layout JSON instead of its path")
    args = ap.parse_args(argv)
    text = build_layout(args.image_topic)
    if args.write:
        layout_path().write_text(text + "\n")
    if args.print:
        print(text)
    elif not args.write:
        print(layout_path())


if __name__ == "__main__":
    main()
