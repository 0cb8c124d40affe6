"""The figures a training run prints mean what they say: the steering fit is an R² against a constant angle
(it may be below 0 for a pilot that drives well its own way), and the drive's score is the share of the distance
driven before first leaving the road (1.0 for clean laps)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from asyncdonkey.parts.sim import ScriptedDriver, Simulator
from asyncdonkey.parts.sim.training import (
    LinearPilot,
    Perturbation,
    collect,
    drive,
    evaluate,
    gray_pool_features,
    train_pilot,
)

from ..examples.example_loader import EXAMPLES

FEATURES = gray_pool_features


@pytest.fixture(scope="module")
def trained():
    return train_pilot(FEATURES, frames=900, dagger_rounds=1, dagger_frames=400, seed=0)


@pytest.fixture(scope="module")
def held_out():
    sim = Simulator(respawn_after_s=0.5)
    sim.reset(s=20.0)
    return collect(sim, ScriptedDriver(sim.track, seed=99), 400, features=FEATURES, perturb=Perturbation(), seed=7)


def test_the_angle_fit_is_an_r2_against_the_constant_angle(trained, held_out):
    pilot, report = trained
    m = evaluate(pilot, held_out, report.baseline_angle)
    assert "skill" not in m
    assert m["angle_r2"] == pytest.approx(1.0 - m["angle_mse"] / m["baseline_angle_mse"])
    assert 0.5 < m["angle_r2"] <= 1.0  # the trained pilot steers much like the driver
    # the constant itself scores 0, whatever its value
    dim = held_out.features.shape[1]
    constant = LinearPilot(np.zeros((dim, 2), np.float32), np.array([report.baseline_angle, 0.3], np.float32), FEATURES)
    assert evaluate(constant, held_out, report.baseline_angle)["angle_r2"] == pytest.approx(0.0, abs=1e-6)
    # steering the other way round from the driver is worse than the constant: below 0
    mirrored = LinearPilot(-pilot.W, -pilot.b, FEATURES)
    assert evaluate(mirrored, held_out, report.baseline_angle)["angle_r2"] < 0


def test_clean_laps_score_the_whole_distance_on_the_road(trained):
    pilot, _ = trained
    sim = Simulator(respawn_after_s=0.5)
    result = drive(sim, pilot, 30.0)
    assert result.clean and result.laps == 1
    assert result.clean_fraction == 1.0
    assert result.clean_distance == result.forward_distance == pytest.approx(result.distance)


def test_a_pilot_that_leaves_the_road_scores_the_share_it_drove_before():
    sim = Simulator(respawn_after_s=0.5)

    def hard_right(image):
        return 1.0, 0.4

    result = drive(sim, hard_right, 20.0)
    assert result.off_track_frames > 0 and result.respawns > 0
    assert 0.0 < result.clean_fraction < 0.5, result
    # the share is what it says: the distance covered before leaving the road, out of the distance covered
    assert result.clean_distance == pytest.approx(result.clean_fraction * result.forward_distance)
    assert 0.0 < result.clean_distance < result.forward_distance


@pytest.mark.subprocess
def test_train_example_prints_no_skill_and_the_share_on_the_road(tmp_path):
    """A pilot trained from a short recording steers its own way (its R² may be below 0) and drives clean."""
    proc = subprocess.run(
        [
            sys.executable,
            str(EXAMPLES / "train.py"),
            "--out",
            str(tmp_path / "m.onnx"),
            "--frames",
            "300",
            "--dagger-frames",
            "300",
            "--check-seconds",
            "30",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "skill" not in proc.stdout
    assert "held-out imitation of the driver: angle R² " in proc.stdout
    assert "clean 100% (the share driven before first leaving the road)" in proc.stdout
    assert (tmp_path / "m.onnx").is_file()
