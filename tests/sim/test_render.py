"""The camera view: a straight road is two lines converging on the vanishing point at the horizon."""

import math
import time

import numpy as np
import pytest

from asyncdonkey.parts.sim import CameraSpec, Simulator, Track

# a long straight: the bottom side of a 40 m x 10 m rounded rectangle runs east for 34 m from the start
STRAIGHT = Track.rounded_rectangle(40.0, 10.0, 3.0, width=1.0)


@pytest.fixture(scope="module")
def sim():
    return Simulator(STRAIGHT)


def _line_fits(img, spec):
    """Fit ``col = a + b * row`` to the white pixels left and right of centre, row by row."""
    f = img.astype(int)
    white = f.min(axis=2) > 170
    left, right = [], []
    for r in range(math.ceil(spec.horizon_row) + 12, spec.height):
        cols = np.flatnonzero(white[r])
        lc, rc = cols[cols < spec.width / 2], cols[cols >= spec.width / 2]
        # a lane line crosses each row as one short run; skip rows where it is cut by the image border
        if 0 < len(lc) < 12 and lc.min() > 0:
            left.append((r, lc.mean()))
        if 0 < len(rc) < 12 and rc.max() < spec.width - 1:
            right.append((r, rc.mean()))
    assert len(left) >= 8 and len(right) >= 8, "both edge lines must be visible over many rows"
    fits = []
    for pts in (left, right):
        rows, cols = np.array(pts).T
        b, a = np.polyfit(rows, cols, 1)
        resid = cols - (a + b * rows)
        assert np.abs(resid).max() < 1.0, "a straight edge line must image as a straight line"
        fits.append((a, b))
    return fits


def _vanishing_point(fits):
    (a1, b1), (a2, b2) = fits
    row = (a2 - a1) / (b1 - b2)
    return row, a1 + b1 * row


def test_frame_shape_type_and_freshness(sim):
    sim.reset(s=1.0)
    a = sim.render()
    b = sim.render()
    assert a.shape == (120, 160, 3) and a.dtype == np.uint8
    assert a is not b and np.array_equal(a, b)  # deterministic, and a new array each time


def test_straight_road_renders_as_two_lines_converging_at_the_horizon(sim):
    spec = sim.camera_spec
    sim.reset(s=1.0)
    img = sim.render()
    (al, bl), (ar, br) = fits = _line_fits(img, spec)
    # the left line leans right going up the image, the right line leans left: they converge
    assert bl < -1.0 and br > 1.0
    assert bl == pytest.approx(-br, rel=0.05)  # symmetric: the car is on the centre line
    row, col = _vanishing_point(fits)
    assert row == pytest.approx(spec.horizon_row, abs=1.0)
    assert col == pytest.approx((spec.width - 1) / 2, abs=1.0)
    # the gap between the lines shrinks towards the horizon
    r_near, r_far = 110, 60
    assert (ar + br * r_near) - (al + bl * r_near) > 2 * ((ar + br * r_far) - (al + bl * r_far))
    # the dashed yellow centre line is in the middle
    f = img.astype(int)
    yellow = (f[..., 0] > 150) & (f[..., 1] > 110) & (f[..., 2] < 110)
    _, xs = np.nonzero(yellow)
    assert len(xs) > 30 and abs(xs.mean() - (spec.width - 1) / 2) < 3


def test_turning_the_car_moves_the_vanishing_point_by_the_pinhole_angle(sim):
    spec = sim.camera_spec
    yaw = 0.15  # car turned left of the road: the road's vanishing point moves right
    sim.reset(s=1.0, heading_error=yaw)
    row, col = _vanishing_point(_line_fits(sim.render(), spec))
    assert row == pytest.approx(spec.horizon_row, abs=1.0)
    # a horizontal direction yaw to the side of the optical axis, in a camera pitched down by p, images at
    # x = f · tan(yaw) / cos(p) from the centre column, on the horizon row
    expected = (spec.width - 1) / 2 + spec.focal_px * math.tan(yaw) / math.cos(math.radians(spec.pitch_deg))
    assert col == pytest.approx(expected, abs=1.0)


def test_a_sideways_offset_keeps_the_vanishing_point_and_shifts_the_lines(sim):
    spec = sim.camera_spec
    sim.reset(s=1.0)
    centred = _line_fits(sim.render(), spec)
    sim.reset(s=1.0, offset=0.2)  # 20 cm right of centre: the road appears shifted left
    shifted = _line_fits(sim.render(), spec)
    row, col = _vanishing_point(shifted)
    assert row == pytest.approx(spec.horizon_row, abs=1.0)
    assert col == pytest.approx((spec.width - 1) / 2, abs=1.0)
    r = 100
    for (a0, b0), (a1, b1) in zip(centred, shifted, strict=True):
        assert (a1 + b1 * r) < (a0 + b0 * r) - 5


def test_sky_above_the_horizon_and_grass_off_the_road(sim):
    spec = sim.camera_spec
    sim.reset(s=1.0)
    img = sim.render().astype(int)
    sky = img[: int(spec.horizon_row) - 1]
    assert (sky[..., 2] > sky[..., 1]).all() and (sky[..., 2] > sky[..., 0]).all()
    # facing away from the road, out over the field: mostly green below the horizon
    x, y, h = STRAIGHT.pose_at(5.0, 1.5)
    sim.set_pose(x, y, h - math.pi / 2)
    ground = sim.render().astype(int)[int(spec.horizon_row) + 3 :]
    green = (ground[..., 1] > ground[..., 0] + 20) & (ground[..., 1] > ground[..., 2] + 20)
    assert green.mean() > 0.95


def test_camera_spec_checks_its_numbers():
    with pytest.raises(ValueError, match="hfov_deg"):
        CameraSpec(hfov_deg=170)
    with pytest.raises(ValueError, match="mount_height"):
        CameraSpec(mount_height=0)


@pytest.mark.realtime
def test_render_is_fast(sim):
    sim.reset(s=1.0)
    times = []
    for i in range(40):
        x, y, h = STRAIGHT.pose_at(i * 0.7, 0.1)
        t = time.perf_counter()
        sim.renderer.render(x, y, h)
        times.append(time.perf_counter() - t)
    # The simulated car renders one frame a tick: the renderer must leave a 20 Hz tick (50 ms) almost whole. About
    # 0.4 ms on an idle core here, but a CI run beside another suite saw a 2.1 ms median, so the bound is what a
    # loaded 2-core machine keeps: a fifth of the tick. A renderer that lost its vectorization (per-pixel Python,
    # hundreds of ms a frame) still fails it.
    assert float(np.median(times)) < 10e-3
