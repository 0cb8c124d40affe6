"""The car's systemd unit, made for the installing user: it names that user and their home (never a `pi` the
Imager no longer makes), starts what exists (the checkout's venv python, our command, car_pi's options), and the
installer refuses what would make a broken or unsafe unit (root, paths systemd would split, no venv)."""

import configparser
import importlib.util
import pwd
import re
import shlex
import sys
from pathlib import Path, PurePosixPath
from types import ModuleType

import pytest
from hypothesis import given
from hypothesis import strategies as st

from asyncdonkey.commands.cli import build_parser

from .example_loader import load_example

ROOT = Path(__file__).resolve().parents[2]
TEMPLATE = ROOT / "examples" / "systemd" / "asyncdonkey-car.service.in"
INSTALLER = ROOT / "examples" / "systemd" / "install_service.py"


def _load_installer() -> ModuleType:
    spec = importlib.util.spec_from_file_location("example_install_service", INSTALLER)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


inst = _load_installer()
ALICE = inst.Target("alice", PurePosixPath("/home/alice"), PurePosixPath("/home/alice/asyncdonkey"))


def unit_for(target, car_args=()):
    return inst.render(TEMPLATE.read_text(), target, list(car_args))


def parse_unit(text):
    parser = configparser.ConfigParser(interpolation=None, strict=True)
    parser.optionxform = str  # systemd keys are case-sensitive
    parser.read_string(text)
    return parser


def systemd_split(command):
    """ExecStart= as systemd reads it: shell-like words and quotes, then %% and $$ each one character again."""
    return [word.replace("%%", "%").replace("$$", "$") for word in shlex.split(command)]


def car_args_of(unit):
    argv = systemd_split(unit["Service"]["ExecStart"])
    return argv[argv.index("--") + 1 :]


@pytest.fixture(scope="module")
def alice_unit():
    return parse_unit(unit_for(ALICE))


def test_the_unit_made_for_alice_names_alice_and_her_home_and_nowhere_pi(alice_unit):
    text = unit_for(ALICE)
    service = alice_unit["Service"]
    assert service["User"] == "alice"
    assert service["WorkingDirectory"] == "/home/alice/asyncdonkey"
    assert shlex.split(service["ExecStart"])[0] == "/home/alice/asyncdonkey/.venv/bin/python"
    assert load_example("car_pi").parse_args(car_args_of(alice_unit))[1].token_file == (
        "/home/alice/.asyncdonkey-web-token"
    )
    # a user or path named pi (car_pi.py, picamera2 and docs/raspberry-pi.md are other names)
    assert not re.search(r"(?<![\w-])pi\b", text), re.search(r".*(?<![\w-])pi\b.*", text)
    assert "/home/pi" not in text
    assert not re.search(r"@[A-Z_]+@", text), "a placeholder left unfilled"


def test_a_home_and_a_checkout_anywhere_are_followed():
    bob = inst.Target("bob", PurePosixPath("/srv/bob"), PurePosixPath("/opt/cars/asyncdonkey"))
    unit = parse_unit(unit_for(bob))
    assert unit["Service"]["User"] == "bob"
    assert unit["Service"]["WorkingDirectory"] == "/opt/cars/asyncdonkey"
    assert shlex.split(unit["Service"]["ExecStart"])[0] == "/opt/cars/asyncdonkey/.venv/bin/python"
    assert "--token-file" in car_args_of(unit) and "/srv/bob/.asyncdonkey-web-token" in car_args_of(unit)


def test_the_service_restarts_on_failure_logs_to_the_journal_and_stops_like_ctrl_c(alice_unit):
    service = alice_unit["Service"]
    assert service["Restart"] == "on-failure" and float(service["RestartSec"]) > 0
    assert service["KillSignal"] == "SIGINT"  # the runtime's clean stop: steering centred, ESC stopped
    assert float(service["TimeoutStopSec"]) >= 5
    assert service["StandardOutput"] == service["StandardError"] == "journal"
    assert "PYTHONUNBUFFERED=1" in service["Environment"].split()
    assert alice_unit["Install"]["WantedBy"] == "multi-user.target"


def test_exec_start_runs_the_venvs_python_on_our_command_with_options_that_exist(alice_unit):
    service = alice_unit["Service"]
    workdir = PurePosixPath(service["WorkingDirectory"])
    argv = systemd_split(service["ExecStart"])
    assert PurePosixPath(argv[0]) == workdir / ".venv" / "bin" / "python"  # the venv made in docs/raspberry-pi.md
    assert argv[1:3] == ["-m", "asyncdonkey.commands"]
    assert importlib.util.find_spec("asyncdonkey.commands.__main__") is not None
    cut = argv.index("--")
    args, unknown = build_parser().parse_known_args(argv[3:cut])
    assert not unknown and args.command == "run"
    assert not Path(args.car).is_absolute() and (ROOT / args.car) == ROOT / "examples" / "car_pi.py"
    _, car_options = load_example("car_pi").parse_args(argv[cut + 1 :])  # exits on an option car_pi lacks
    assert car_options.camera == "picamera2" and car_options.web
    # the phone's bookmark survives reboots: the token is kept in a file in the service user's home
    assert PurePosixPath(car_options.token_file).is_relative_to(PurePosixPath("/home/alice"))


def test_settings_and_options_after_the_lone_dash_dash_reach_car_pi_after_the_units_own():
    extra = ["STEERING_LEFT_PWM=470", "THROTTLE_FORWARD_PWM=480", "--model", "models/pilot.onnx", "--camera", "opencv"]
    unit = parse_unit(unit_for(ALICE, extra))
    cfg, options = load_example("car_pi").parse_args(car_args_of(unit))
    assert cfg.STEERING_LEFT_PWM == 470 and cfg.THROTTLE_FORWARD_PWM == 480
    assert options.model == "models/pilot.onnx"
    assert options.camera == "opencv"  # a later --camera replaces the unit's picamera2
    assert options.web and options.token_file == "/home/alice/.asyncdonkey-web-token"


def test_with_js_the_gamepad_drives_and_no_web_page_or_token_file_is_set():
    unit = parse_unit(inst.render(TEMPLATE.read_text(), ALICE, ["JOYSTICK_THROTTLE_AXIS=3"], gamepad=True))
    cfg, options = load_example("car_pi").parse_args(car_args_of(unit))
    assert options.js and not options.web and options.token_file is None
    assert options.camera == "picamera2" and cfg.JOYSTICK_THROTTLE_AXIS == 3
    assert unit["Service"]["User"] == "alice"


@pytest.mark.parametrize(
    ("arg", "quoted"),
    [
        ("STEERING_LEFT_PWM=470", "STEERING_LEFT_PWM=470"),
        ("NAME=a b", '"NAME=a b"'),
        ("100%", '"100%%"'),
        ("$HOME", '"$$HOME"'),
        ('say "hi"', '"say \\"hi\\""'),
        ("", '""'),
    ],
)
def test_a_car_argument_is_quoted_for_systemd(arg, quoted):
    assert inst.systemd_quote(arg) == quoted


@given(st.text(alphabet=st.characters(exclude_characters="\n\r\x00", exclude_categories=("Cs",))))
def test_any_car_argument_without_a_line_break_is_read_back_by_systemd_as_given(arg):
    assert systemd_split(f"run -- {inst.systemd_quote(arg)}") == ["run", "--", arg]


def test_a_car_argument_with_a_line_break_is_refused_in_one_line():
    with pytest.raises(inst.InstallError, match=r"cannot hold a line break: 'A=1\\nB=2'"):
        inst.systemd_quote("A=1\nB=2")


@pytest.mark.parametrize(
    ("home", "checkout"),
    [("/home/al ice", "/home/alice/asyncdonkey"), ("/home/alice", "/home/alice/my%car"), ("home/alice", "/opt/a")],
)
def test_paths_systemd_would_split_or_expand_are_refused_naming_the_path(home, checkout):
    with pytest.raises(inst.InstallError, match=r"must be an absolute path") as refused:
        unit_for(inst.Target("alice", PurePosixPath(home), PurePosixPath(checkout)))
    assert str(refused.value).count("\n") == 0
    assert home in str(refused.value) or checkout in str(refused.value)


def test_the_car_runs_as_the_caller_or_who_called_sudo_and_never_as_root():
    nobody = pwd.getpwnam("nobody")
    assert inst.car_user(None, {}, nobody.pw_uid) == "nobody"
    assert inst.car_user(None, {"SUDO_USER": "alice"}, 0) == "alice"
    assert inst.car_user("carol", {}, 0) == "carol"
    for requested, environ in ((None, {}), (None, {"SUDO_USER": "root"}), ("root", {"SUDO_USER": "alice"})):
        with pytest.raises(inst.InstallError, match="must not run as root"):
            inst.car_user(requested, environ, 0)


def test_print_renders_the_unit_for_the_user_and_their_home_from_the_password_database(tmp_path, capsys):
    nobody = pwd.getpwnam("nobody")
    assert inst.main(["--print", "--user", "nobody", "--checkout", str(tmp_path)]) == 0
    unit = parse_unit(capsys.readouterr().out)
    assert unit["Service"]["User"] == "nobody"
    assert unit["Service"]["WorkingDirectory"] == str(tmp_path.resolve())
    assert car_args_of(unit)[car_args_of(unit).index("--token-file") + 1] == f"{nobody.pw_dir}/.asyncdonkey-web-token"


def test_an_unknown_user_or_a_missing_venv_stops_with_one_line_and_installs_nothing(tmp_path, capsys):
    assert inst.main(["--print", "--user", "no-such-user-here"]) == 1
    assert capsys.readouterr().err == "install_service: no user 'no-such-user-here' in the password database\n"
    target = inst.Target("alice", PurePosixPath("/home/alice"), PurePosixPath(tmp_path))
    with pytest.raises(inst.InstallError, match=rf"{tmp_path}/.venv/bin/python does not exist: make the venv"):
        inst.install(unit_for(target), target, as_root=False, start=True)


def test_the_install_steps_put_the_unit_in_place_before_systemd_reads_enables_and_restarts_it():
    steps = inst.install_steps(Path("/tmp/x/asyncdonkey-car.service"), as_root=False, start=True)
    assert [s[0] for s in steps] == ["sudo"] * 4
    assert steps[0][1:] == [
        *("install", "-m", "0644", "-o", "root", "-g", "root"),
        *("/tmp/x/asyncdonkey-car.service", "/etc/systemd/system/asyncdonkey-car.service"),
    ]
    assert [s[1:] for s in steps[1:]] == [
        ["systemctl", "daemon-reload"],
        ["systemctl", "enable", "asyncdonkey-car"],
        ["systemctl", "restart", "asyncdonkey-car"],
    ]
    as_root_no_start = inst.install_steps(Path("/tmp/u"), as_root=True, start=False)
    assert [s[0] for s in as_root_no_start] == ["install", "systemctl", "systemctl"]
    assert as_root_no_start[-1] == ["systemctl", "enable", "asyncdonkey-car"]


def test_the_setup_guide_installs_this_unit_for_its_user_and_covers_the_car_on_its_own():
    guide = (ROOT / "docs" / "raspberry-pi.md").read_text()
    assert "examples/systemd/install_service.py" in guide
    for command in ("journalctl -u asyncdonkey-car", "systemctl restart asyncdonkey-car"):
        assert command in guide, command
    assert "--system-site-packages" in guide and "python3-picamera2" in guide
    assert "/home/pi" not in guide and "pi@" not in guide and "User=pi" not in guide
    for step in ("bluetoothctl", "jstest /dev/input/js0", "nmcli", "power_save off", "scp ", "make test-aarch64"):
        assert step in guide, step
