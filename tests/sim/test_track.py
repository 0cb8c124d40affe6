"""Track geometry and lap counting."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.parts.sim import CarParams, LapCounter, ScriptedDriver, Simulator, Track, default_track

OVAL = Track.oval(straight=8.0, radius=3.0, width=1.0)
DEFAULT = default_track()


def test_oval_length_and_start_pose():
    assert OVAL.length == pytest.approx(2 * 8.0 + 2 * math.pi * 3.0, rel=1e-3)
    x, y, h = OVAL.pose_at(0.0)
    assert (x, y) == pytest.approx((-4.0, -3.0), abs=1e-6)
    assert h == pytest.approx(0.0, abs=1e-9)  # heading east along the bottom straight


def test_projection_on_straight_signs_cte_right_positive():
    # bottom straight runs east at y = -3: south of it is the right-hand side
    p = OVAL.project(0.0, -3.25)
    assert p.cte == pytest.approx(0.25, abs=1e-9)
    assert p.s == pytest.approx(4.0, abs=1e-6)
    assert p.heading == pytest.approx(0.0, abs=1e-9)
    assert OVAL.project(0.0, -2.6).cte == pytest.approx(-0.4, abs=1e-9)


def test_projection_on_bend_measures_radial_distance():
    # right half circle centred (4, 0), radius 3; a point at radius 2.5 is 0.5 m left (inside) of the line
    p = OVAL.project(4.0 + 2.5 * math.cos(0.3), 2.5 * math.sin(0.3))
    assert p.cte == pytest.approx(-0.5, abs=2e-3)
    assert p.s == pytest.approx(8.0 + 3.0 * (math.pi / 2 + 0.3), abs=0.01)


@settings(max_examples=60, deadline=None)
@given(s=st.floats(0.0, DEFAULT.length, exclude_max=True), off=st.floats(-0.45, 0.45))
def test_pose_at_and_project_are_inverse(s, off):
    x, y, _ = DEFAULT.pose_at(s, off)
    p = DEFAULT.project(x, y)
    assert p.cte == pytest.approx(off, abs=0.01)
    ds = (p.s - s + DEFAULT.length / 2) % DEFAULT.length - DEFAULT.length / 2
    assert abs(ds) < 0.06


def test_default_track_is_drivable_and_does_not_cross_itself():
    assert 35 < DEFAULT.length < 60
    assert DEFAULT.min_radius() > 2 * CarParams().min_turn_radius
    pts = DEFAULT.points
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    n = len(pts)
    idx = np.arange(n)
    gap = np.abs(idx[:, None] - idx[None, :])
    along = np.minimum(gap, n - gap) * (DEFAULT.length / n)
    # points far apart along the road are at least two road widths apart on the ground
    assert d[along > 3.0].min() > 2 * DEFAULT.width
    # it turns both ways
    k = [DEFAULT.curvature_at(s) for s in np.arange(0, DEFAULT.length, 0.25)]
    assert max(k) > 0.2 and min(k) < -0.2


def test_bad_track_input_is_named():
    with pytest.raises(ValueError, match="width"):
        Track([(0, 0), (1, 0), (1, 1)], width=0)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        Track([(0, 0), (1, 0)], width=1)
    with pytest.raises(ValueError, match="non-finite"):
        Track([(0, 0), (1, float("nan")), (1, 1)], width=1)


# ------------------------------------------------------------------------------------------ laps
def _feed(counter: LapCounter, ss):
    return [counter.update(s) for s in ss]


def test_full_forward_lap_counts_once():
    c = LapCounter(10.0, s0=0.05)
    laps = _feed(c, np.arange(0.05, 25.0, 0.1))
    assert laps[-1] == 2
    assert c.progress == pytest.approx(24.95)
    # the count rises exactly when the start line is passed: s = 0.05 + 0.1 i reaches 10 at i = 100
    assert laps.index(1) == 100 and laps.index(2) == 200


def test_jitter_at_the_start_line_counts_once():
    c = LapCounter(10.0, s0=0.05)
    _feed(c, np.arange(0.05, 9.9, 0.1))
    assert c.laps == 0
    rng = np.random.default_rng(1)
    for _ in range(200):  # dither across the line
        c.update((10.0 + rng.uniform(-0.05, 0.05)) % 10.0)
    assert c.laps == 1
    _feed(c, np.arange(0.1, 9.9, 0.1))
    assert c.laps == 1


def test_reverse_crossing_does_not_count():
    c = LapCounter(10.0, s0=0.5)
    _feed(c, np.arange(0.5, -1.0, -0.1) % 10.0)  # back over the line
    assert c.laps == 0
    _feed(c, np.arange(-1.0, 0.5, 0.1) % 10.0)  # and forward over it again
    assert c.laps == 0
    _feed(c, (np.arange(0.5, -12.0, -0.1)) % 10.0)  # a whole lap in reverse
    assert c.laps == 0
    # driving forward again only counts once the old high-water mark is passed
    _feed(c, np.arange(-12.0, 9.0, 0.1) % 10.0)
    assert c.laps == 0
    _feed(c, np.arange(9.0, 10.5, 0.1) % 10.0)
    assert c.laps == 1


def test_jumps_are_not_progress():
    c = LapCounter(10.0, s0=0.0, max_jump=2.0)
    c.update(0.1)
    c.update(4.9)  # a teleport of 4.8 m
    c.update(9.9)  # and another
    c.update(0.2)  # a normal step over the line: progress had no credit for the jumps
    assert c.laps == 0


def test_simulator_counts_laps_at_the_line_not_at_the_start():
    """Starting 1 m behind the line, rolling over it starts lap 1; the lap counts one full lap later."""
    sim = Simulator(DEFAULT)
    sim.reset(s=DEFAULT.length - 1.0, speed=1.5)
    driver = ScriptedDriver(DEFAULT, noise=0.0)
    crossed_at = None
    laps = []
    for _ in range(2000):
        tel = sim.telemetry()
        tel = sim.step(0.05, *driver.run(tel.x, tel.y, tel.heading))
        laps.append(tel.laps)
        if crossed_at is None and sim.progress >= DEFAULT.length:
            crossed_at = len(laps)
        if sim.progress >= 2 * DEFAULT.length + 1.0:
            break
    assert crossed_at is not None and laps[crossed_at - 1] == 0
    first = laps.index(1)
    # the lap was counted on the step that crossed the line a second time
    assert sim.progress >= 2 * DEFAULT.length
    assert laps[-1] == 1
    assert 0.8 * DEFAULT.length < (first - crossed_at) * 0.05 * 2.5 < 1.5 * DEFAULT.length


def test_teleport_and_respawn_keep_laps_without_credit():
    sim = Simulator(DEFAULT, respawn_after_s=0.5)
    sim.set_pose(*DEFAULT.pose_at(DEFAULT.length - 0.3))
    for _ in range(10):
        sim.step(0.05, 0.0, 0.5)
    # it crossed the line onto new ground, but a teleport earns no lap
    assert sim.progress > sim.laps.best - 1e-9 > 0 and sim.telemetry().laps == 0
    # drive off the road at full lock: the car is put back on the centre line, stopped, facing the road
    for _ in range(60):
        tel = sim.step(0.05, 1.0, 0.6)
    assert sim.respawns >= 1
    assert abs(tel.cte) <= DEFAULT.half_width
