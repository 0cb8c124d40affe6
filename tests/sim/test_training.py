"""Training a linear pilot on simulator data: it beats a constant angle on held-out data and drives laps."""

import numpy as np
import pytest

from asyncdonkey.parts.sim import ScriptedDriver, Simulator
from asyncdonkey.parts.sim.training import (
    Perturbation,
    collect,
    drive,
    evaluate,
    fit_ridge,
    gray_pool_features,
    samples_from_tub,
    train_pilot,
)

FEATURES = gray_pool_features


@pytest.fixture(scope="module")
def trained():
    return train_pilot(FEATURES, frames=900, dagger_rounds=1, dagger_frames=400, seed=0)


def test_ridge_recovers_a_linear_map_on_raw_feature_scales():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 12)) * rng.uniform(0.01, 100, 12) + rng.uniform(-50, 50, 12)
    w = rng.normal(size=(12, 2))
    y = x @ w + np.array([0.3, -0.2])
    wf, bf = fit_ridge(x, y, alpha=1e-9)
    assert np.abs(x @ wf + bf - y).max() < 1e-3 * np.abs(y).max()
    # a large penalty shrinks towards the mean
    ws, bs = fit_ridge(x, y, alpha=1e6)
    assert np.abs(x @ ws + bs - y.mean(axis=0)).max() < 0.01 * np.abs(y - y.mean(axis=0)).max()


def test_pilot_beats_a_constant_angle_on_held_out_driving(trained):
    pilot, report = trained
    # held out: a different track position, driver seed and pulse sequence than anything trained on
    sim = Simulator(respawn_after_s=0.5)
    sim.reset(s=20.0)
    held = collect(sim, ScriptedDriver(sim.track, seed=99), 400, features=FEATURES, perturb=Perturbation(), seed=7)
    m = evaluate(pilot, held, report.baseline_angle)
    assert m["angle_mse"] < 0.5 * m["baseline_angle_mse"], m
    assert m["throttle_mse"] < 0.01


def test_trained_pilot_drives_a_lap_in_closed_loop(trained):
    pilot, _ = trained
    sim = Simulator(respawn_after_s=0.5)
    sim.reset(s=10.0)
    result = drive(sim, pilot, 30.0)
    assert result.clean, result
    assert result.distance > sim.track.length
    assert result.laps == 1
    assert result.max_abs_cte < 0.6 * sim.track.half_width


def test_samples_from_a_recorded_tub_match_the_session(tmp_path):
    from asyncdonkey.parts.tub import TubWriter

    sim = Simulator()
    driver = ScriptedDriver(sim.track, seed=3)
    writer = TubWriter(
        tmp_path / "tub",
        inputs=["cam/image_array", "user/angle", "user/throttle", "sim/cte"],
        types=["image_array", "float", "float", "float"],
    )
    frames, angles = [], []
    for _ in range(60):
        tel = sim.telemetry()
        image = sim.render()
        angle, throttle = driver.run(tel.x, tel.y, tel.heading)
        writer.run(image, angle, throttle, tel.cte)
        frames.append(image)
        angles.append(angle)
        sim.step(0.05, angle, throttle)
    writer.shutdown()
    s = samples_from_tub(tmp_path / "tub", features=FEATURES)
    assert len(s) == 60
    np.testing.assert_allclose(s.angle, angles)
    assert np.isfinite(s.cte).all()
    # JPEG changes pixels a little, the pooled features barely
    direct = np.array([FEATURES(f) for f in frames])
    assert np.abs(s.features - direct).max() < 0.03
    with pytest.raises(ValueError, match="pilot/angle"):
        samples_from_tub(tmp_path / "tub", features=FEATURES, angle_key="pilot/angle")
