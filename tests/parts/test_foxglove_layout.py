"""The Foxglove layout: in the form the Foxglove app imports (``configById`` and a tree of splits), every panel on
a topic that a recording of the car holds, and only panels for the channels the car has."""

from __future__ import annotations

import json
from collections.abc import Iterator

import numpy as np
import pytest
from mcap.reader import make_reader

from asyncdonkey.loop import Vehicle
from asyncdonkey.parts.mcap import McapRecorder
from asyncdonkey.parts.mcap.layout import (
    GPS_CHANNELS,
    PANEL_TYPES,
    build_layout,
    layout_for_vehicle,
    layout_path,
    main,
    vehicle_channels,
)


class Camera:
    def __init__(self):
        self.k = 0

    def run(self):
        self.k += 1
        return np.full((120, 160, 3), self.k * 10 % 250, np.uint8)


class Controller:
    def run(self):
        return 0.2, 0.3, "local_angle"


class Pilot:
    def run(self, image):
        return -0.1, 0.25


class Gps:
    def run(self):
        return 45.5, 7.7


class Motor:
    """An actuator: the loop measures its sensing-to-actuation latency."""

    def run(self, throttle):
        return None

    def safe_state_sync(self):
        pass


def donkeycar(gps: bool = False) -> Vehicle:
    """A Donkeycar car: camera, controller, pilot, steering and throttle (and a GPS if asked)."""
    v = Vehicle()
    v.add(Camera(), outputs=["cam/image_array"], name="camera")
    v.add(Controller(), outputs=["user/angle", "user/throttle", "user/mode"], name="controller")
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], name="pilot")
    if gps:
        v.add(Gps(), outputs=list(GPS_CHANNELS), name="gps")
    v.add(Motor(), inputs=["user/throttle"], actuator=True, name="motor")
    return v


# ------------------------------------------------------------------------------------- reading it as the app does
def leaves(node) -> Iterator[str]:
    """The panel ids of a layout tree: a leaf is an id, a split has ``first``, ``second`` and a direction."""
    if isinstance(node, str):
        yield node
        return
    assert node["direction"] in ("row", "column")
    assert 0 < node["splitPercentage"] < 100
    yield from leaves(node["first"])
    yield from leaves(node["second"])


def check_importable(layout: dict) -> None:
    assert {"configById", "globalVariables", "userNodes", "playbackConfig", "layout"} <= set(layout)
    assert "version" not in layout and "content" not in layout  # not foxglove-sdk's own form
    ids = list(leaves(layout["layout"]))
    assert len(ids) == len(set(ids))
    assert set(ids) == set(layout["configById"])  # every leaf has a config, every config is shown
    for panel_id, config in layout["configById"].items():
        kind, bang, _ = panel_id.partition("!")
        assert bang and kind in PANEL_TYPES, panel_id
        assert config["foxglovePanelTitle"]


def topic_paths(layout: dict) -> list[str]:
    """Every message path a panel reads (``/topic`` or ``/topic.field``)."""
    paths = []
    for panel_id, config in layout["configById"].items():
        kind = panel_id.partition("!")[0]
        if kind == "Image":
            paths += [config["imageMode"]["imageTopic"], *config["imageMode"]["annotations"]]
        elif kind == "Plot":
            paths += [series["value"] for series in config["paths"]]
            assert all(series["enabled"] and series["timestampMethod"] == "receiveTime" for series in config["paths"])
        elif kind == "RawMessages":
            paths.append(config["topicPath"])
        elif kind == "Map":
            paths.append(config["followTopic"])
    return paths


async def record(v: Vehicle, path) -> dict[str, tuple[str, bytes]]:
    """Drive ``v`` a few ticks with the recorder; the first message of each topic of the file."""
    rec = McapRecorder(path, v, fsync=False)
    v.add(rec, name="mcap")
    await v.run(rate_hz=20, max_loop_count=5)
    rec.shutdown()
    first: dict[str, tuple[str, bytes]] = {}
    with open(path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            first.setdefault(channel.topic, (channel.message_encoding, message.data))
    return first


def check_recorded(layout: dict, first: dict[str, tuple[str, bytes]]) -> None:
    for path in topic_paths(layout):
        topic, _, field = path.partition(".")
        assert topic in first, f"{path}: the recording has no {topic} (it has {sorted(first)})"
        if field:
            encoding, data = first[topic]
            assert encoding == "json" and field in json.loads(data), path


# ------------------------------------------------------------------------------------------------------ tests
def test_the_shipped_layout_is_the_built_one_in_the_form_foxglove_imports():
    text = layout_path().read_text().strip()
    assert text == build_layout()
    layout = json.loads(text)
    check_importable(layout)
    assert layout["playbackConfig"] == {"speed": 1}
    # a Donkeycar car without GPS
    assert text == layout_for_vehicle(donkeycar())
    assert not any(pid.startswith("Map!") for pid in layout["configById"])
    cam = layout["configById"]["Image!camera"]["imageMode"]
    assert cam == {"imageTopic": "/cam/image_array", "annotations": {"/cam/image_array/steering": {"visible": True}}}
    steering = layout["configById"]["Plot!steering"]
    assert [s["value"] for s in steering["paths"]] == ["/user/angle.value", "/pilot/angle.value"]
    assert (steering["minYValue"], steering["maxYValue"], steering["showLegend"]) == (-1, 1, True)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.parametrize("gps", [False, True], ids=["no-gps", "gps"])
async def test_every_panel_reads_a_topic_the_car_records(tmp_path, gps):
    v = donkeycar(gps)
    layout = json.loads(layout_for_vehicle(v))
    check_importable(layout)
    first = await record(v, tmp_path / "drive.mcap")
    check_recorded(layout, first)
    assert ("Map!gps" in layout["configById"]) == gps
    assert ("/gps/fix" in first) == gps


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_car_without_pilot_or_actuators_gets_no_panels_for_them(tmp_path):
    v = Vehicle()
    v.add(Camera(), outputs=["cam/image_array"])
    v.add(Controller(), outputs=["user/angle", "user/throttle", "user/mode"])
    assert vehicle_channels(v) == {"cam/image_array", "user/angle", "user/throttle", "user/mode"}
    layout = json.loads(layout_for_vehicle(v))
    check_importable(layout)
    panels = layout["configById"]
    assert set(panels) == {
        "Image!camera",
        "Plot!steering",
        "Plot!throttle",
        "Plot!timing",
        "RawMessages!parts",
        "RawMessages!mode",
    }
    assert [s["label"] for s in panels["Plot!steering"]["paths"]] == ["user"]
    assert panels["Plot!steering"]["foxglovePanelTitle"] == "steering: user"
    check_recorded(layout, await record(v, tmp_path / "drive.mcap"))


def test_panels_follow_the_channels_given():
    only_gps = json.loads(build_layout(GPS_CHANNELS, timing=False))
    check_importable(only_gps)
    assert list(only_gps["configById"]) == ["Map!gps"] and only_gps["layout"] == "Map!gps"
    no_angles = json.loads(build_layout(["cam/image_array", "pilot/throttle"], actuators=False))
    check_importable(no_angles)
    assert no_angles["configById"]["Image!camera"]["imageMode"]["annotations"] == {}  # nothing drawn over it
    assert "Plot!steering" not in no_angles["configById"] and "RawMessages!latency" not in no_angles["configById"]
    assert [s["value"] for s in no_angles["configById"]["Plot!throttle"]["paths"]] == ["/pilot/throttle.value"]


def test_the_command_line(tmp_path, capsys):
    main([])
    assert capsys.readouterr().out.strip() == str(layout_path())
    main(["--print"])
    assert capsys.readouterr().out.strip() == layout_path().read_text().strip()
    main(["--print", "--gps"])
    assert "Map!gps" in json.loads(capsys.readouterr().out)["configById"]
    main(["--print", "--channels", "cam/image_array", "user/angle", "--no-actuators"])
    assert set(json.loads(capsys.readouterr().out)["configById"]) == {
        "Image!camera",
        "Plot!steering",
        "Plot!timing",
        "RawMessages!parts",
    }
    out = tmp_path / "car.json"
    main(["--write", str(out), "--image-topic", "/front/image"])
    assert capsys.readouterr().out == ""
    layout = json.loads(out.read_text())
    check_importable(layout)
    assert layout["configById"]["Image!camera"]["imageMode"]["imageTopic"] == "/front/image"
