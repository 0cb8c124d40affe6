"""asyncdonkey.testing exposes every device model by name, loading each module only when used."""

import subprocess
import sys

import pytest

import asyncdonkey.testing as testing


def test_every_exported_name_resolves_to_the_object_in_its_module():
    for name in testing.__all__:
        obj = getattr(testing, name)
        assert obj is not None
        module = getattr(obj, "__module__", None)
        # device models live in asyncdonkey.testing; the virtual clock is runtime code it re-exports
        where = ("asyncdonkey.testing", "asyncdonkey.clock.virtual_loop")
        assert module is None or module.startswith(where), (name, module)


def test_the_virtual_loop_is_exported_from_asyncdonkey_testing():
    import asyncdonkey.clock.virtual_loop as core

    for name in core.__all__:
        assert getattr(testing, name) is getattr(core, name)


def test_the_lazy_name_lists_match_each_models_module():
    """The names are listed here so nothing is imported until used; they must not drift from the modules."""
    import importlib

    for module, names in testing._LAZY.items():
        mod = importlib.import_module(f"asyncdonkey.testing.{module}")
        assert sorted(names) == sorted(mod.__all__), module


def test_unknown_names_raise_attribute_error():
    try:
        testing.NoSuchModel  # noqa: B018
    except AttributeError as exc:
        assert "NoSuchModel" in str(exc)
    else:
        raise AssertionError("expected AttributeError")


@pytest.mark.subprocess
def test_the_virtual_clock_alone_does_not_import_opencv():
    code = "import sys, asyncdonkey.testing as t; t.VirtualClockLoop; print('cv2' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
