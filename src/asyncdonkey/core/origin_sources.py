"""Declared selectors: parts that say which input each output came from, so their outputs are dated by it.

Why. The age rule dates a part's outputs by the **oldest** of its inputs (``docs/provenance.md``): nothing
outside the part can tell which inputs it used, and "oldest" never makes data look younger than it is. A
selector such as ``DriveMode`` picks one input and passes it on; dated by the oldest input, the driver's fresh
throttle in ``user`` mode would carry the age of a pilot that stopped long ago, and the stale-command failsafe
would cut a driver. So a selector **declares** what it passed on, and only a declaration can make an output
younger than the oldest input: nothing is guessed from the order, the names or the identity of the values.

The declaration: a method ``output_sources(*args)`` on the part, called after each ``run()`` that returned
outputs, with the same arguments. It returns one entry per output, in order:

* an input's index (its position in ``inputs=``): the output is that input's value, or made from it alone;
* a tuple of indices: made from those inputs (dated by the oldest of them);
* ``None``: the default rule (the oldest of all inputs).

An index of a channel read for its age (``"x@age"``) means that channel. A declaration that is not one entry per
output, or names an index the part does not have, fails that call naming the part (``on_error`` applies).

Parts we cannot change are declared from here, **by their interface** (the class name and the names of
``run()``'s parameters, with the number of inputs and outputs the car adds them with), since a Donkeycar template
defines its classes inside each car's own script:

* Donkeycar's template ``DriveMode``, ``run(mode, user_angle|user_steering, user_throttle,
  pilot_angle|pilot_steering, pilot_throttle)``, 5 inputs and 2 outputs (``complete.py``, ``basic.py``), and the
  simulator template's ``run(mode, user_angle, user_throttle, user_brake, pilot_angle, pilot_throttle,
  pilot_brake)``, 7 inputs and 3 outputs. Declared as Donkeycar's code chooses: ``mode == 'user'``, the user's
  values; ``mode == 'local_angle'``, the pilot's angle and the user's throttle (and brake); any other mode the
  pilot's values (a ``0.0`` it puts in for a pilot value that is falsy is dated by that pilot input);
* Donkeycar's template ``UserPilotCondition``, ``run(mode, user_image, pilot_image)``, 3 inputs and 3 outputs:
  the two run conditions from the mode, the image it shows from the image it picked.

A class with one of these names and parameters that does something else must declare its own
``output_sources``; a part that picks one input and does not declare gets the oldest origin (the safe side).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["OutputSources", "declared_sources"]

#: what a declaration returns for each output: an input index, a tuple of them, or ``None`` (the default rule)
Source = int | tuple[int, ...] | None
OutputSources = Callable[..., Sequence[Source]]

_USER_ANGLE = ("user_angle", "user_steering")
_PILOT_ANGLE = ("pilot_angle", "pilot_steering")


def declared_sources(part: Any, n_inputs: int, n_outputs: int) -> OutputSources | None:
    """The part's declaration (its own ``output_sources``, or one from here for a known interface), or ``None``."""
    own = getattr(part, "output_sources", None)
    if callable(own):
        return own  # type: ignore[no-any-return]
    return _known_interface(part, n_inputs, n_outputs)


def _known_interface(part: Any, n_inputs: int, n_outputs: int) -> OutputSources | None:
    """A declaration for a Donkeycar template class used unchanged, recognised by its interface (module docstring)."""
    name = type(part).__name__
    if name not in ("DriveMode", "UserPilotCondition"):
        return None
    params = _run_parameters(part)
    if params is None:
        return None
    if name == "DriveMode" and (n_inputs, n_outputs) == (5, 2) and _is_drive_mode(params, brake=False):
        return _template_drive_mode
    if name == "DriveMode" and (n_inputs, n_outputs) == (7, 3) and _is_drive_mode(params, brake=True):
        return _simulator_drive_mode
    if (
        name == "UserPilotCondition"
        and (n_inputs, n_outputs) == (3, 3)
        and params
        == (
            "mode",
            "user_image",
            "pilot_image",
        )
    ):
        return _user_pilot_condition(part)
    return None


def _run_parameters(part: Any) -> tuple[str, ...] | None:
    """The names of ``run()``'s positional parameters (``self`` excluded), or ``None`` if it has others."""
    try:
        sig = inspect.signature(part.run)
    except (AttributeError, TypeError, ValueError):
        return None
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    if any(p.kind not in kinds for p in sig.parameters.values()):
        return None
    return tuple(sig.parameters)


def _is_drive_mode(params: tuple[str, ...], brake: bool) -> bool:
    if brake:
        return (
            len(params) == 7
            and params[0] == "mode"
            and params[1] in _USER_ANGLE
            and params[2:4] == ("user_throttle", "user_brake")
            and params[4] in _PILOT_ANGLE
            and params[5:] == ("pilot_throttle", "pilot_brake")
        )
    return (
        len(params) == 5
        and params[0] == "mode"
        and params[1] in _USER_ANGLE
        and params[2] == "user_throttle"
        and params[3] in _PILOT_ANGLE
        and params[4] == "pilot_throttle"
    )


# Donkeycar's comparisons, as its code makes them: ``mode == 'user'``, ``mode == 'local_angle'``, else the pilot
_DM_USER, _DM_ANGLE, _DM_PILOT = (1, 2), (3, 2), (3, 4)
_SIM_USER, _SIM_ANGLE, _SIM_PILOT = (1, 2, 3), (4, 2, 3), (4, 5, 6)


def _template_drive_mode(mode: Any, *_: Any) -> tuple[int, ...]:
    if mode == "user":
        return _DM_USER
    if mode == "local_angle":
        return _DM_ANGLE
    return _DM_PILOT


def _simulator_drive_mode(mode: Any, *_: Any) -> tuple[int, ...]:
    if mode == "user":
        return _SIM_USER
    if mode == "local_angle":
        return _SIM_ANGLE
    return _SIM_PILOT


def _user_pilot_condition(part: Any) -> OutputSources:
    user, pilot = (0, 0, 1), (0, 0, 2)

    def sources(mode: Any, *_: Any) -> tuple[int, ...]:
        if mode == "user":
            return user
        return pilot if getattr(part, "show_pilot_image", False) else user

    return sources
