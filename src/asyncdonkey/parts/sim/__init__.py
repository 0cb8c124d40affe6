"""A simulated Donkey car: closed track, kinematic bicycle model, 160x120 camera, lap counting.

Runs anywhere (numpy + OpenCV), fast enough for tests on the virtual clock and for collecting training data
headless. See ``docs/simulator.md`` for the model, the camera, the channels and the collect → train → drive →
replay tutorial.

* :class:`Simulator` — synchronous: ``step(dt, angle, throttle)``, ``render()``, ``reset()``.
* :class:`SimCar` — the drive-loop parts: ``car.camera`` (``cam/image_array``), ``car.telemetry``
  (:data:`TELEMETRY_OUTPUTS`), and ``car`` itself taking ``angle, throttle``.
* :class:`ScriptedDriver` — a pure-pursuit "user" giving ``user/angle, user/throttle``.
"""

from .driver import ScriptedDriver
from .parts import TELEMETRY_OUTPUTS, SimCamera, SimCar, SimTelemetry
from .physics import BicycleModel, CarParams, CarState
from .render import CameraRenderer, CameraSpec, TrackTexture
from .simulator import Simulator, Telemetry
from .track import LapCounter, Projection, Track, default_track

__all__ = [
    "TELEMETRY_OUTPUTS",
    "BicycleModel",
    "CameraRenderer",
    "CameraSpec",
    "CarParams",
    "CarState",
    "LapCounter",
    "Projection",
    "ScriptedDriver",
    "SimCamera",
    "SimCar",
    "SimTelemetry",
    "Simulator",
    "Telemetry",
    "Track",
    "TrackTexture",
    "default_track",
]
