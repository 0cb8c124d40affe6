""".ci/check-aarch64 checks what pyproject.toml lists: every dependency and every extra a car may install."""

import importlib.machinery
import importlib.util
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_script():
    loader = importlib.machinery.SourceFileLoader("check_aarch64", str(ROOT / ".ci" / "check-aarch64"))
    spec = importlib.util.spec_from_loader("check_aarch64", loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def test_the_requirements_are_the_base_and_every_car_extra_of_pyproject():
    script = load_script()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    checked = {req for req, _ in script.requirements()}
    assert set(project["dependencies"]) <= checked
    car_extras = set(project["optional-dependencies"]) - set(script.DEV_ONLY)
    assert {"tflite", "zenoh", "mcap"} <= car_extras
    own = script._name(project["name"])
    for extra in car_extras:
        items = project["optional-dependencies"][extra]
        assert {r for r in items if script._name(r) != own} <= checked, extra
        # an extra made of our other extras (asyncdonkey[a,b]) is covered by theirs, never resolved as a wheel
        for ref in (r for r in items if script._name(r) == own):
            assert not any(script._name(r) == own for r in checked), ref
            assert set(ref[ref.index("[") + 1 : ref.index("]")].split(",")) <= car_extras, ref
    dev_only = {r for extra in script.DEV_ONLY for r in project["optional-dependencies"][extra]}
    assert not {r for r in dev_only if script._name(r) in {"pytest", "playwright", "ruff"}} & checked
    assert not script.EXCLUDED  # a package without aarch64 wheels is reported, with its reason, here and in docs


def test_the_platform_tags_cover_bookworms_glibc():
    script = load_script()
    assert "manylinux2014_aarch64" in script.PLATFORMS
    assert {f"manylinux_2_{m}_aarch64" for m in (17, 27, 28, 36)} <= set(script.PLATFORMS)
    assert not any("2_37" in p or "x86" in p for p in script.PLATFORMS)  # nothing newer than Bookworm's glibc
    assert script.PYTHONS == ("3.11", "3.13")
