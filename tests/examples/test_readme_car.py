"""The README's example car runs as written, from any directory: its pilot is found beside the car file.

It used to name ``examples/models/sim_pilot.onnx`` relative to the working directory, so ``asyncdonkey run
~/asyncdonkey/mycar.py`` from another directory failed with ``examples/models/sim_pilot.onnx does not exist``.
"""

from __future__ import annotations

import re
from pathlib import Path

from asyncdonkey.commands.cli import load_car

ROOT = Path(__file__).resolve().parents[2]


def readme_car() -> str:
    """The README's ``mycar.py``: the Python block that defines ``build()``."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.DOTALL)
    [car] = [b for b in blocks if "def build(" in b]
    return car


def test_the_readme_car_finds_its_pilot_from_another_directory(tmp_path, monkeypatch):
    checkout = tmp_path / "checkout"  # the car file where the README puts it: the checkout's top directory
    checkout.mkdir()
    (checkout / "examples").symlink_to(ROOT / "examples")
    (checkout / "mycar.py").write_text(readme_car())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    vehicle, module = load_car(checkout / "mycar.py")
    assert checkout / "examples" / "models" / "sim_pilot.onnx" == module.PILOT
    assert [type(e.part).__name__ for e in vehicle.parts][1] == "OnnxPilot"
