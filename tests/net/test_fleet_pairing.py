"""``zenoh-pair`` for one car and for a fleet, and ``top``'s screen: what the user sees and what gets written.

No network here: the configs are read back as files; the fleet's rules at work are in ``test_pilot_server.py``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import stat
import sys

import pytest

from asyncdonkey.commands.cli import main
from asyncdonkey.commands.zenoh import SORT_KEYS, add_zenoh_parsers
from asyncdonkey.extras import install_command
from asyncdonkey.parts.zenoh.fleet import SORT_KEYS as FLEET_SORT_KEYS
from asyncdonkey.parts.zenoh.fleet import car_state, render_fleet
from asyncdonkey.parts.zenoh.pairing import PairExists, make_fleet


def _json5(path):
    return json.loads(path.read_text().split("\n", 1)[1])  # first line is a // comment


def test_pairing_again_refuses_to_overwrite_and_names_the_files(tmp_path, capsys):
    out = tmp_path / "p"
    assert main(["zenoh-pair", str(out), "--car", "c1", "--pilot", "laptop", "--view", "base"]) == 0
    ca = (out / "ca" / "ca.pem").read_bytes()
    capsys.readouterr()
    assert main(["zenoh-pair", str(out), "--car", "c1", "--pilot", "laptop"]) == 2
    err = capsys.readouterr().err
    assert "refusing to overwrite" in err and str(out / "ca" / "ca-key.pem") in err and "--force" in err
    assert (out / "ca" / "ca.pem").read_bytes() == ca  # nothing was replaced: the view's certificate still works
    assert main(["zenoh-pair", str(out), "--car", "c1", "--pilot", "laptop", "--force"]) == 0
    assert (out / "ca" / "ca.pem").read_bytes() != ca


def test_the_defaults_used_are_printed(tmp_path, capsys):
    assert main(["zenoh-pair", str(tmp_path / "p")]) == 0
    text = capsys.readouterr().out
    assert "defaults used" in text and "car name 'car1'" in text and "pilot name 'pilot'" in text
    assert "car host 'localhost'" in text
    # the window every machine's clock must be in: from a few minutes ago, 825 days long
    line = next(t for t in text.splitlines() if t.startswith("certificates valid from"))
    start = datetime.datetime.strptime(line.split()[3] + " " + line.split()[4], "%Y-%m-%d %H:%M")
    now = datetime.datetime.now(datetime.UTC).replace(tzinfo=None)
    assert datetime.timedelta(0) <= now - start <= datetime.timedelta(minutes=7) and "(NTP)" in line
    assert main(["zenoh-pair", str(tmp_path / "q"), "--car", "a", "--pilot", "b", "--car-host", "10.0.0.2"]) == 0
    assert "defaults used" not in capsys.readouterr().out


def test_fleet_options_are_checked(tmp_path, capsys):
    assert main(["zenoh-pair", str(tmp_path), "--fleet", "--cars", "a", "b"]) == 2
    assert "--fleet needs --server NAME" in capsys.readouterr().err
    assert main(["zenoh-pair", str(tmp_path), "--fleet", "--server", "s"]) == 2
    assert "--fleet needs --cars" in capsys.readouterr().err
    assert main(["zenoh-pair", str(tmp_path), "--fleet", "--cars", "a", "--server", "s", "--car", "x"]) == 2
    assert "--car pair one car" in capsys.readouterr().err
    assert main(["zenoh-pair", str(tmp_path), "--cars", "a", "b"]) == 2
    assert "add --fleet" in capsys.readouterr().err
    assert main(["zenoh-pair", str(tmp_path), "--fleet", "--cars", "a", "a", "--server", "s"]) == 2
    assert "must differ" in capsys.readouterr().err


def test_fleet_pairing_writes_a_server_that_confines_each_car_to_its_keys(tmp_path, capsys):
    out = tmp_path / "fleet"
    argv = ["zenoh-pair", str(out), "--fleet", "--cars", "car1", "car2", "--server", "gpu", "--view", "base"]
    assert main([*argv, "--server-host", "10.0.0.9", "--port", "7450"]) == 0
    text = capsys.readouterr().out
    assert "certificates valid from" in text
    assert "server gpu" in text and "car    car1" in text and "car    car2" in text and "view   base" in text
    server = _json5(out / "server" / "server.json5")
    assert server["mode"] == "router" and server["listen"]["endpoints"] == ["tls/0.0.0.0:7450"]
    assert server["transport"]["link"]["tls"]["enable_mtls"] is True
    acl = server["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["car1-in"]["key_exprs"] == ["cars/car1/**"] and rules["car1-in"]["flows"] == ["ingress"]
    assert rules["car2-out"]["key_exprs"] == ["cars/car2/**"] and rules["car2-out"]["flows"] == ["egress"]
    assert {"id": "car-car1", "cert_common_names": ["car1"]} in acl["subjects"]
    assert {"rules": ["car1-in", "car1-out"], "subjects": ["car-car1"]} in acl["policies"]
    assert "put" not in rules["views-subscribe"]["messages"]  # a view puts nothing
    for car in ("car1", "car2"):
        cfg = _json5(out / car / "car.json5")
        assert cfg["connect"]["endpoints"] == ["tls/10.0.0.9:7450"] and cfg["listen"]["endpoints"] == []
        commands = next(r for r in cfg["access_control"]["rules"] if r["id"] == "pilot-commands")
        assert f"cars/{car}/pilot/command" in commands["key_exprs"]
        assert {"id": "pilot-host", "cert_common_names": ["gpu"]} in cfg["access_control"]["subjects"]
        assert stat.S_IMODE(os.stat(out / car / f"{car}-key.pem").st_mode) == 0o600
    assert _json5(out / "base" / "base.json5")["mode"] == "client"
    assert not any((out / d / "ca-key.pem").exists() for d in ("server", "car1", "car2", "base"))
    with pytest.raises(PairExists, match="refusing to overwrite"):
        make_fleet(out, cars=["car3"], server="gpu")  # the CA and the server's files exist


def test_every_option_has_help_and_top_says_what_it_shows():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    add_zenoh_parsers(sub)
    for name in ("zenoh-pair", "top", "pilot-server"):
        p = sub.choices[name]
        assert p.description, name
        missing = [a.dest for a in p._actions if a.dest != "help" and not a.help]
        assert missing == [], (name, missing)
    assert "STALE" in sub.choices["top"].description and "SILENT" in sub.choices["top"].description
    assert SORT_KEYS == FLEET_SORT_KEYS


@pytest.mark.parametrize(
    ("argv", "module"),
    [
        (["top", "--once", "0"], "zenoh"),
        (["pilot-server", "m.onnx", "--cars", "a"], "zenoh"),
        (["zenoh-pair", "out"], "cryptography"),
    ],
)
def test_a_missing_extra_prints_the_install_line(monkeypatch, capsys, tmp_path, argv, module):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, module, None)  # import fails as if it were not installed
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert install_command("zenoh") in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def _doc(latency=None, **ages):
    return {"hz": 20.0, "mode": "local", "latency_p99_ms": latency, "ages_ms": ages, "parts": {"X": 1.0}}


def test_top_marks_stale_and_silent_cars_and_sorts_them():
    now = 100.0
    cars = {
        "cars/a": (_doc(30.0, **{"pilot/throttle": 40.0}), now - 0.5),
        "cars/b": (_doc(5.0, **{"pilot/throttle": 10.0}), now - 0.2),
        "cars/c": (_doc(None, **{"pilot/throttle": 20.0}), now - 9.0),  # no status for 9 s
        "cars/d": (_doc(12.0, **{"pilot/throttle": 400.0}), now - 0.1),  # its command is 400 ms old
    }
    assert car_state(cars["cars/a"][0], 0.5) == "live" and car_state(cars["cars/d"][0], 0.1) == "STALE"
    assert car_state(cars["cars/c"][0], 9.0) == "SILENT"

    def order(sort: str) -> list[str]:
        screen = render_fleet(cars, now, sort=sort, parts=False)
        return [line.split()[0] for line in screen.splitlines()[2:]]

    assert order("name") == ["cars/a", "cars/b", "cars/c", "cars/d"]
    assert order("latency") == ["cars/a", "cars/d", "cars/b", "cars/c"]  # slowest first, unknown last
    assert order("age") == ["cars/d", "cars/a", "cars/c", "cars/b"]  # oldest first
    screen = render_fleet(cars, now, sort="latency", stale_ms=250)
    summary = "asyncdonkey top - 4 cars seen, 2 live, 0 no command, 1 stale, 1 silent (sorted by latency)"
    assert screen.splitlines()[0] == summary
    rows = {line.split()[0]: line.split() for line in screen.splitlines()[2:] if line.startswith("cars/")}
    assert rows["cars/c"][1] == "SILENT" and rows["cars/d"][1] == "STALE" and rows["cars/a"][3] == "30.0"
    assert "parts ms" in screen and "parts ms" not in render_fleet(cars, now, parts=False)
    with pytest.raises(ValueError, match="--sort"):
        render_fleet(cars, now, sort="speed")
