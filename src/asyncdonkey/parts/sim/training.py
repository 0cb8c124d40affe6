"""Collect, fit, evaluate: a light pilot learned from simulator driving, numpy only, in seconds.

The pilot is linear: ``[angle, throttle] = features(image) @ W + b``, where ``features`` turns a 160x120 RGB
frame into a short vector (by default the one :mod:`asyncdonkey.pilot_export` builds into the ONNX graph, so
the exported model computes exactly what was trained). Ridge regression fits ``W`` and ``b`` in closed form.

Why it can drive at all: a linear model only copies the "user" on states the user visited, and a user who
never strays from the centre line never shows what to do after a mistake. So collection injects mistakes
(DART-style): while recording, short steering pulses are added to what the car *executes*, while the label
stays what the driver commands, i.e. the correction. After a first fit, DAgger-lite rounds let the learnt
pilot drive (with the same pulses), label its frames with the driver's command for the pose it got itself
into, and refit on everything.

Everything here is synchronous and deterministic for a given seed; it uses :class:`~.simulator.Simulator`
directly, without an event loop.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .driver import ScriptedDriver
from .simulator import Simulator

__all__ = [
    "DriveResult",
    "LinearPilot",
    "Samples",
    "collect",
    "drive",
    "evaluate",
    "fit_ridge",
    "samples_from_tub",
    "train_pilot",
]

logger = logging.getLogger(__name__)

FeatureFn = Callable[[np.ndarray], np.ndarray]
"""``image (120, 160, 3) uint8 RGB -> (D,) float32``."""

PilotFn = Callable[[np.ndarray], tuple[float, float]]
"""``image -> (angle, throttle)``."""


@dataclass
class Samples:
    """Feature vectors with the driver's commands (the labels) and where the car was."""

    features: np.ndarray  # (N, D) float32
    angle: np.ndarray  # (N,)
    throttle: np.ndarray  # (N,)
    cte: np.ndarray  # (N,)

    def __len__(self) -> int:
        return len(self.angle)

    @property
    def targets(self) -> np.ndarray:
        return np.column_stack([self.angle, self.throttle])

    @staticmethod
    def concat(parts: Sequence[Samples]) -> Samples:
        return Samples(
            np.concatenate([p.features for p in parts]),
            np.concatenate([p.angle for p in parts]),
            np.concatenate([p.throttle for p in parts]),
            np.concatenate([p.cte for p in parts]),
        )


@dataclass
class LinearPilot:
    """``[angle, throttle] = features(image) @ W + b``, clipped to Donkeycar's ranges."""

    W: np.ndarray  # (D, 2) float32
    b: np.ndarray  # (2,) float32
    features: FeatureFn

    def predict(self, feats: np.ndarray) -> np.ndarray:
        """Rows of features → rows of ``[angle, throttle]`` (unclipped)."""
        return feats @ self.W + self.b

    def __call__(self, image: np.ndarray) -> tuple[float, float]:
        a, t = self.features(image) @ self.W + self.b
        return max(-1.0, min(1.0, float(a))), max(-1.0, min(1.0, float(t)))


@dataclass
class Perturbation:
    """Steering pulses injected into what the car executes (not into the labels) while collecting.

    A pulse starts with probability ``rate_hz / hz`` per frame, lasts ``duration`` seconds (uniform in the
    range) and adds ``amplitude`` (uniform, random sign) to the executed angle.
    """

    rate_hz: float = 0.5
    amplitude: tuple[float, float] = (0.3, 0.8)
    duration: tuple[float, float] = (0.15, 0.5)


def collect(
    sim: Simulator,
    driver: ScriptedDriver,
    frames: int,
    *,
    features: FeatureFn,
    hz: float = 20.0,
    perturb: Perturbation | None = None,
    pilot: PilotFn | None = None,
    seed: int = 0,
) -> Samples:
    """Drive ``frames`` frames at ``hz`` and record ``features(frame)`` with the driver's command as label.

    The car executes the driver's command, or the ``pilot``'s if given (DAgger: the driver only labels),
    plus the ``perturb`` pulses. The simulator should respawn the car when it leaves the road
    (``Simulator(respawn_after_s=...)``), or a pilot that fails early wastes the rest of the budget on grass.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0 / hz
    feats: list[np.ndarray] = []
    angles = np.empty(frames)
    throttles = np.empty(frames)
    ctes = np.empty(frames)
    pulse_left = 0
    pulse = 0.0
    for i in range(frames):
        tel = sim.telemetry()
        image = sim.render()
        f = features(image)
        label_angle, label_throttle = driver.run(tel.x, tel.y, tel.heading)
        feats.append(f)
        angles[i], throttles[i], ctes[i] = label_angle, label_throttle, tel.cte
        angle, throttle = pilot(image) if pilot is not None else (label_angle, label_throttle)
        if perturb is not None:
            if pulse_left <= 0 and rng.random() < perturb.rate_hz * dt:
                pulse = float(rng.uniform(*perturb.amplitude)) * (1 if rng.random() < 0.5 else -1)
                pulse_left = max(1, round(float(rng.uniform(*perturb.duration)) * hz))
            if pulse_left > 0:
                angle += pulse
                pulse_left -= 1
        sim.step(dt, max(-1.0, min(1.0, angle)), throttle)
    return Samples(np.asarray(feats, dtype=np.float32), angles, throttles, ctes)


def samples_from_tub(
    paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    features: FeatureFn,
    image_key: str = "cam/image_array",
    angle_key: str = "user/angle",
    throttle_key: str = "user/throttle",
) -> Samples:
    """Samples from recorded tubs (ours or Donkeycar's): ``features(image)`` with the recorded user command.

    Deleted records are skipped (the reader does that). ``cte`` is taken from ``sim/cte`` when the session
    recorded it, else NaN. Raises ``ValueError`` naming the tub when a needed key was not recorded.
    """
    from ..tub import Tub

    if isinstance(paths, str | os.PathLike):
        paths = [paths]
    feats: list[np.ndarray] = []
    angles: list[float] = []
    throttles: list[float] = []
    ctes: list[float] = []
    for path in paths:
        tub = Tub(path)
        missing = [k for k in (image_key, angle_key, throttle_key) if k not in tub.inputs]
        if missing:
            raise ValueError(f"tub {os.fspath(path)!r} has no {missing} (it recorded {tub.inputs})")
        for rec in tub:
            angle, throttle = rec[angle_key], rec[throttle_key]
            if angle is None or throttle is None:
                continue
            feats.append(features(rec[image_key]))
            angles.append(float(angle))
            throttles.append(float(throttle))
            cte = rec.get("sim/cte")
            ctes.append(math.nan if cte is None else float(cte))
    if not feats:
        raise ValueError(f"no usable records in {[os.fspath(p) for p in paths]}")
    return Samples(np.asarray(feats, np.float32), np.asarray(angles), np.asarray(throttles), np.asarray(ctes))


def fit_ridge(x: np.ndarray, y: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Ridge regression ``y ≈ x @ W + b`` (intercept not penalised). Features are standardised for the
    solve, so ``alpha`` means the same whatever their scale; the returned ``W, b`` apply to raw features."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    mu = x.mean(axis=0)
    sd = x.std(axis=0)
    sd[sd < 1e-8] = 1.0
    z = (x - mu) / sd
    ym = y.mean(axis=0)
    n, d = z.shape
    if d <= n:
        gram = z.T @ z
        gram[np.diag_indices_from(gram)] += alpha * n
        wz = np.linalg.solve(gram, z.T @ (y - ym))
    else:  # more features than samples: the dual form solves an n x n system instead of d x d
        kern = z @ z.T
        kern[np.diag_indices_from(kern)] += alpha * n
        wz = z.T @ np.linalg.solve(kern, y - ym)
    w = wz / sd[:, None]
    b = ym - mu @ w
    return w.astype(np.float32), b.astype(np.float32)


def evaluate(pilot: LinearPilot, samples: Samples, baseline_angle: float) -> dict[str, float]:
    """Angle and throttle mean squared error on ``samples``, beside a constant-angle baseline.

    ``angle_r2`` is the coefficient of determination of the steering fit against that baseline,
    ``1 - angle_mse / baseline_angle_mse``: 1 when the pilot steers exactly as the labels do, 0 when it does no
    better than always steering ``baseline_angle``, negative when worse. It measures imitation of the driver who
    labelled ``samples`` on those frames, not driving: a pilot that steers its own way can drive clean laps and
    still score below 0 (it then disagrees with the driver more than a constant angle does), so whether a pilot
    drives is :func:`drive`'s :attr:`DriveResult.clean_fraction`, not this figure.
    """
    pred = pilot.predict(samples.features)
    pa = np.clip(pred[:, 0], -1, 1)
    pt = np.clip(pred[:, 1], -1, 1)
    mse = float(np.mean((pa - samples.angle) ** 2))
    base = float(np.mean((baseline_angle - samples.angle) ** 2))
    return {
        "angle_mse": mse,
        "baseline_angle_mse": base,
        "angle_mae": float(np.mean(np.abs(pa - samples.angle))),
        "throttle_mse": float(np.mean((pt - samples.throttle) ** 2)),
        "angle_r2": 1.0 - mse / base if base > 0 else 0.0,
    }


@dataclass
class DriveResult:
    """A closed-loop drive: laps completed, how far off centre, how often it left the road.

    ``forward_distance`` is the distance covered forward along the road, step by step (``distance`` is the net
    progress, which a car turning circles keeps near 0); ``clean_distance`` is the part of it covered before
    the car first left the road. :attr:`clean_fraction`, their ratio, is the drive's score: 1.0 for a drive
    that never left the road, 0.5 for one that left it halfway, near 0 for one that left it at once and went
    on moving (a car circling on the grass and back over the road gains no credit once it has left it).
    """

    seconds: float
    laps: int
    distance: float
    mean_abs_cte: float
    max_abs_cte: float
    off_track_frames: int
    respawns: int
    forward_distance: float = 0.0
    clean_distance: float = 0.0

    @property
    def clean_fraction(self) -> float:
        """Share of the forward distance driven before first leaving the road, in [0, 1] (0 for a car that never
        moved forward)."""
        if self.forward_distance <= 0:
            return 0.0
        return self.clean_distance / self.forward_distance

    @property
    def clean(self) -> bool:
        return self.off_track_frames == 0 and self.respawns == 0


def drive(
    sim: Simulator, pilot: PilotFn, seconds: float, *, hz: float = 20.0, throttle: float | None = None
) -> DriveResult:
    """Let ``pilot`` drive from the simulator's current pose for ``seconds`` (``throttle`` overrides its
    throttle, like Donkeycar's ``local_angle`` mode)."""
    dt = 1.0 / hz
    n = round(seconds * hz)
    start = sim.progress
    ctes = np.empty(n)
    off = 0
    forward = clean = 0.0
    left_road = abs(sim.cte) > sim.track.half_width
    respawns0 = sim.respawns
    for i in range(n):
        a, t = pilot(sim.render())
        before = sim.progress
        tel = sim.step(dt, a, t if throttle is None else throttle)
        ctes[i] = abs(tel.cte)
        off += tel.off_track
        left_road = left_road or tel.off_track
        gained = max(0.0, sim.progress - before)
        forward += gained
        if not left_road:
            clean += gained
    return DriveResult(
        seconds=n * dt,
        laps=sim.telemetry().laps,
        distance=sim.progress - start,
        mean_abs_cte=float(ctes.mean()) if n else 0.0,
        max_abs_cte=float(ctes.max()) if n else 0.0,
        off_track_frames=int(off),
        respawns=sim.respawns - respawns0,
        forward_distance=forward,
        clean_distance=clean,
    )


@dataclass
class TrainReport:
    """What :func:`train_pilot` did."""

    samples: int
    alpha: float
    rounds: list[dict[str, float]] = field(default_factory=list)
    baseline_angle: float = 0.0


def train_pilot(
    features: FeatureFn,
    *,
    sim_factory: Callable[[], Simulator] | None = None,
    frames: int = 1500,
    dagger_rounds: int = 1,
    dagger_frames: int = 800,
    alphas: Sequence[float] = (0.01, 0.03, 0.1, 0.3, 1.0),
    seed: int = 0,
    hz: float = 20.0,
    initial: Samples | None = None,
) -> tuple[LinearPilot, TrainReport]:
    """Collect with the scripted driver (with recovery pulses), fit, then ``dagger_rounds`` DAgger rounds.

    ``initial`` replaces the first collection (e.g. :func:`samples_from_tub`); DAgger rounds still run in the
    simulator, which is how a pilot trained on a careful recording learns to recover. ``alpha`` is chosen on
    a held-out tail of the first data set. Returns the pilot and a report.
    """
    make = sim_factory or (lambda: Simulator(respawn_after_s=0.5))
    sim = make()
    driver = ScriptedDriver(sim.track, seed=seed, rate_hz=hz)
    perturb = Perturbation()
    if initial is not None:
        data = initial
    else:
        data = collect(sim, driver, frames, features=features, hz=hz, perturb=perturb, seed=seed + 1)
    split = int(len(data) * 0.8)
    train = _subset(data, slice(0, split))
    val = _subset(data, slice(split, None))
    baseline = float(train.angle.mean())
    best = None
    for alpha in alphas:
        w, b = fit_ridge(train.features, train.targets, alpha)
        score = evaluate(LinearPilot(w, b, features), val, baseline)["angle_mse"]
        if best is None or score < best[0]:
            best = (score, alpha)
    assert best is not None
    alpha = best[1]
    w, b = fit_ridge(data.features, data.targets, alpha)
    pilot = LinearPilot(w, b, features)
    report = TrainReport(samples=len(data), alpha=alpha, baseline_angle=baseline)
    report.rounds.append({"round": 0, "samples": len(data), "val_angle_mse": best[0]})
    parts = [data]
    for r in range(1, dagger_rounds + 1):
        sim = make()
        sim.reset(s=float(np.random.default_rng(seed + 10 * r).uniform(0, sim.track.length)))
        more = collect(
            sim, driver, dagger_frames, features=features, hz=hz, perturb=perturb, pilot=pilot, seed=seed + 10 * r + 1
        )
        # frames from off the road (before a respawn) are not what a pilot should learn from: drop them
        parts.append(_subset(more, np.abs(more.cte) <= sim.track.half_width))
        data = Samples.concat(parts)
        w, b = fit_ridge(data.features, data.targets, alpha)
        pilot = LinearPilot(w, b, features)
        report.rounds.append({"round": r, "samples": len(data), "pilot_respawns": float(sim.respawns)})
    report.samples = len(data)
    return pilot, report


def _subset(s: Samples, idx: slice | np.ndarray) -> Samples:
    return Samples(s.features[idx], s.angle[idx], s.throttle[idx], s.cte[idx])


def gray_pool_features(image: np.ndarray, *, top: int = 40, pool: int = 8) -> np.ndarray:
    """Stand-in features: grayscale in [0, 1] below the horizon, averaged over ``pool``x``pool`` blocks."""
    g = image[top:].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) / 255.0
    h, w = g.shape
    h2, w2 = h // pool, w // pool
    g = g[: h2 * pool, : w2 * pool].reshape(h2, pool, w2, pool).mean(axis=(1, 3))
    return g.ravel()
