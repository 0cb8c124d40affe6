"""The kinematic bicycle model and the scripted driver on it."""

import math

import numpy as np
import pytest

from asyncdonkey.parts.sim import BicycleModel, CarParams, CarState, ScriptedDriver, Simulator, default_track


def _drive(model, commands, dt=0.05, state=None):
    state = state or CarState()
    out = []
    for a, t in commands:
        state = model.step(state, a, t, dt)
        out.append(state)
    return out


def test_same_commands_give_bit_identical_states():
    rng = np.random.default_rng(3)
    commands = [(float(a), float(t)) for a, t in rng.uniform(-1, 1, (400, 2))]
    a = _drive(BicycleModel(), commands)
    b = _drive(BicycleModel(), commands)
    assert a == b
    assert a[-1] != _drive(BicycleModel(), [*commands[:-1], (0.0, 0.0)])[-1]


def test_throttle_gives_first_order_speed_response():
    p = CarParams()
    m = BicycleModel(p)
    s = CarState()
    s = m.step(s, 0.0, 0.5, p.motor_tau)
    assert s.speed == pytest.approx(0.5 * p.max_speed * (1 - math.exp(-1)), rel=1e-9)
    s = m.step(s, 0.0, 0.5, 10 * p.motor_tau)
    assert s.speed == pytest.approx(0.5 * p.max_speed, rel=1e-3)
    # distance is the exact integral of the speed: straight along +x
    assert s.y == pytest.approx(0.0, abs=1e-12) and s.heading == 0.0
    expected = 0.5 * p.max_speed * (11 * p.motor_tau - p.motor_tau * (1 - math.exp(-11)))
    assert s.x == pytest.approx(expected, rel=1e-9)
    # full reverse is limited to reverse_ratio of max speed
    s = m.step(s, 0.0, -1.0, 20 * p.motor_tau)
    assert s.speed == pytest.approx(-p.reverse_ratio * p.max_speed, rel=1e-3)
    # and commands beyond the range are clipped, not amplified
    assert m.step(CarState(), 0.0, 7.0, 1.0) == m.step(CarState(), 0.0, 1.0, 1.0)


def test_full_lock_right_drives_the_minimum_circle_clockwise():
    p = CarParams()
    m = BicycleModel(p)
    s = CarState(speed=1.0)
    path = _drive(m, [(1.0, 0.25)] * 200, dt=0.02, state=s)
    steady = path[50:]
    assert all(st.steer == pytest.approx(p.max_steer) for st in steady)
    xy = np.array([(st.x, st.y) for st in steady])
    # least-squares circle: x² + y² + D x + E y + F = 0
    a = np.column_stack([xy, np.ones(len(xy))])
    d, e, _ = np.linalg.lstsq(a, -(xy**2).sum(axis=1), rcond=None)[0]
    centre = np.array([-d / 2, -e / 2])
    radii = np.hypot(*(xy - centre).T)
    assert radii.mean() == pytest.approx(p.min_turn_radius, rel=1e-3)
    assert radii.std() < 1e-6
    # positive angle steers right: heading decreases (clockwise)
    assert path[1].heading < path[0].heading < 0
    # beyond full lock is full lock
    assert m.step(s, 3.0, 0.25, 1.0) == m.step(s, 1.0, 0.25, 1.0)


def test_steering_moves_at_the_servo_rate():
    p = CarParams(steer_rate_deg_s=200.0)
    m = BicycleModel(p)
    s = m.step(CarState(), -1.0, 0.0, 0.05)
    assert s.steer == pytest.approx(-math.radians(10.0))
    s = m.step(s, -1.0, 0.0, 0.2)
    assert s.steer == pytest.approx(-p.max_steer)


def test_sub_steps_make_results_nearly_independent_of_dt():
    m = BicycleModel()
    a = _drive(m, [(0.4, 0.6)] * 40, dt=0.05)[-1]
    b = _drive(m, [(0.4, 0.6)] * 200, dt=0.01)[-1]
    assert (a.x, a.y, a.heading, a.speed) == pytest.approx((b.x, b.y, b.heading, b.speed), abs=1e-9)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "left", [0.1]])
def test_bad_commands_raise_a_named_error(bad):
    with pytest.raises(ValueError, match="angle"):
        BicycleModel().step(CarState(), bad, 0.0, 0.05)
    with pytest.raises(ValueError, match="throttle"):
        BicycleModel().step(CarState(), 0.0, bad, 0.05)


def test_none_commands_are_neutral():
    assert BicycleModel().step(CarState(speed=1.0), None, None, 0.1) == BicycleModel().step(
        CarState(speed=1.0), 0.0, 0.0, 0.1
    )


def test_bad_params_are_named():
    with pytest.raises(ValueError, match="max_steer_deg"):
        CarParams(max_steer_deg=95)
    with pytest.raises(ValueError, match="wheelbase"):
        CarParams(wheelbase=0)


def test_scripted_driver_drives_three_laps_without_leaving_the_road():
    track = default_track()
    sim = Simulator(track)
    driver = ScriptedDriver(track, seed=7)
    worst = 0.0
    for _ in range(int(100 / 0.05)):
        tel = sim.telemetry()
        tel = sim.step(0.05, *driver.run(tel.x, tel.y, tel.heading))
        worst = max(worst, abs(tel.cte))
        assert not tel.off_track
        if tel.laps == 3:
            break
    assert tel.laps == 3
    assert worst < 0.25 * track.width
    assert sim.time < 90  # about 2 m/s: a person driving carefully


def test_scripted_driver_recovers_from_an_offset_start():
    track = default_track()
    sim = Simulator(track)
    sim.reset(s=2.0, offset=0.35, heading_error=-0.3, speed=1.0)  # right of centre, pointing further right
    driver = ScriptedDriver(track, noise=0.0)
    ctes = []
    for _ in range(80):
        tel = sim.telemetry()
        tel = sim.step(0.05, *driver.run(tel.x, tel.y, tel.heading))
        ctes.append(tel.cte)
    assert max(abs(c) for c in ctes) < track.half_width
    assert abs(ctes[-1]) < 0.05
