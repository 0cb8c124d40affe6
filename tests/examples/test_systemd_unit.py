"""examples/systemd/asyncdonkey-car.service starts what exists: the venv's python, our command, car_pi's options."""

import configparser
import importlib.util
import shlex
from pathlib import Path, PurePosixPath

import pytest

from asyncdonkey.commands.cli import build_parser

from .example_loader import load_example

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "examples" / "systemd" / "asyncdonkey-car.service"


@pytest.fixture(scope="module")
def unit():
    parser = configparser.ConfigParser(interpolation=None, strict=True)
    parser.optionxform = str  # systemd keys are case-sensitive
    parser.read_string(UNIT.read_text())
    return parser


def test_the_service_restarts_on_failure_logs_to_the_journal_and_stops_like_ctrl_c(unit):
    service = unit["Service"]
    assert service["Restart"] == "on-failure" and float(service["RestartSec"]) > 0
    assert service["KillSignal"] == "SIGINT"  # the runtime's clean stop: steering centred, ESC stopped
    assert float(service["TimeoutStopSec"]) >= 5
    assert service["User"] == "pi"
    assert service["StandardOutput"] == service["StandardError"] == "journal"
    assert "PYTHONUNBUFFERED=1" in service["Environment"].split()
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_exec_start_runs_the_venvs_python_on_our_command_with_options_that_exist(unit):
    service = unit["Service"]
    workdir = PurePosixPath(service["WorkingDirectory"])
    argv = shlex.split(service["ExecStart"])
    assert PurePosixPath(argv[0]) == workdir / ".venv" / "bin" / "python"  # the venv made in docs/raspberry-pi.md
    assert argv[1:3] == ["-m", "asyncdonkey.commands"]
    assert importlib.util.find_spec("asyncdonkey.commands.__main__") is not None
    cut = argv.index("--")
    run_args, car_args = argv[3:cut], argv[cut + 1 :]
    args, unknown = build_parser().parse_known_args(run_args)
    assert not unknown and args.command == "run"
    car = ROOT / args.car  # relative to WorkingDirectory, the checkout
    assert not Path(args.car).is_absolute() and car.is_file() and car == ROOT / "examples" / "car_pi.py"
    car_pi = load_example("car_pi")
    _, car_options = car_pi.parse_args(car_args)  # exits on an option car_pi does not have
    assert car_options.camera == "picamera2" and car_options.web
    # the phone's bookmark survives reboots: the token is kept in a file in the service user's home
    assert PurePosixPath(car_options.token_file).is_relative_to(PurePosixPath("/home") / service["User"])


def test_the_setup_guide_installs_and_reads_this_unit():
    guide = (ROOT / "docs" / "raspberry-pi.md").read_text()
    assert "examples/systemd/asyncdonkey-car.service" in guide
    for command in ("systemctl enable", "journalctl -u asyncdonkey-car", "systemctl restart asyncdonkey-car"):
        assert command in guide, command
    assert "--system-site-packages" in guide and "python3-picamera2" in guide
