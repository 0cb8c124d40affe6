"""GPS part: the local projection against geodesics, positions from the NMEA model on the virtual clock,
corrupt sentences counted and skipped, unplug/replug keeping the origin."""

from __future__ import annotations

import asyncio
import math
import time
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey import Vehicle
from asyncdonkey.clock import get_clock
from asyncdonkey.parts.gps import Gps, LocalProjection
from asyncdonkey.testing.serial_peers import NmeaPeer


def vincenty_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Geodesic distance on WGS84 (Vincenty's inverse formula), an independent reference for the tests."""
    a, f = 6378137.0, 1 / 298.257223563
    b = a * (1 - f)
    big_l = math.radians(lon2 - lon1)
    u1 = math.atan((1 - f) * math.tan(math.radians(lat1)))
    u2 = math.atan((1 - f) * math.tan(math.radians(lat2)))
    su1, cu1, su2, cu2 = math.sin(u1), math.cos(u1), math.sin(u2), math.cos(u2)
    lam = big_l
    for _ in range(200):
        sl, cl = math.sin(lam), math.cos(lam)
        ss = math.hypot(cu2 * sl, cu1 * su2 - su1 * cu2 * cl)
        if ss == 0:
            return 0.0
        cs = su1 * su2 + cu1 * cu2 * cl
        sigma = math.atan2(ss, cs)
        sa = cu1 * cu2 * sl / ss
        c2a = 1 - sa * sa
        c2sm = cs - 2 * su1 * su2 / c2a if c2a else 0.0
        c = f / 16 * c2a * (4 + f * (4 - 3 * c2a))
        prev = lam
        lam = big_l + (1 - c) * f * sa * (sigma + c * ss * (c2sm + c * cs * (-1 + 2 * c2sm * c2sm)))
        if abs(lam - prev) < 1e-13:
            break
    u_sq = c2a * (a * a - b * b) / (b * b)
    big_a = 1 + u_sq / 16384 * (4096 + u_sq * (-768 + u_sq * (320 - 175 * u_sq)))
    big_b = u_sq / 1024 * (256 + u_sq * (-128 + u_sq * (74 - 47 * u_sq)))
    ds = (
        big_b
        * ss
        * (
            c2sm
            + big_b / 4 * (cs * (-1 + 2 * c2sm * c2sm) - big_b / 6 * c2sm * (-3 + 4 * ss * ss) * (-3 + 4 * c2sm * c2sm))
        )
    )
    return b * big_a * (sigma - ds)


def dms(d: int, m: int, s: float) -> float:
    return math.copysign(abs(d) + m / 60 + s / 3600, d)


def test_reference_geodesic_matches_the_published_flinders_peak_example():
    # Vincenty (1975) / Geoscience Australia: Flinders Peak to Buninyong, 54 972.271 m
    d = vincenty_m(dms(-37, 57, 3.72030), dms(144, 25, 29.52440), dms(-37, 39, 10.15610), dms(143, 55, 35.38390))
    assert d == pytest.approx(54972.271, abs=0.001)


@settings(max_examples=200, deadline=None)
@given(
    st.floats(min_value=-75, max_value=75),
    st.floats(min_value=-179, max_value=179),
    st.floats(min_value=0, max_value=2 * math.pi),
    st.floats(min_value=1.0, max_value=1000.0),
)
def test_local_xy_distances_agree_with_geodesics_to_a_millimetre_within_a_kilometre(lat0, lon0, bearing, dist):
    proj = LocalProjection(lat0, lon0)
    # walk `dist` metres in direction `bearing` (from north, clockwise) with a first-order step, then measure
    m_per_deg_lat = 111_132.954 - 559.822 * math.cos(2 * math.radians(lat0))
    m_per_deg_lon = 111_412.84 * math.cos(math.radians(lat0))
    lat = lat0 + dist * math.cos(bearing) / m_per_deg_lat
    lon = lon0 + dist * math.sin(bearing) / m_per_deg_lon
    x, y = proj.to_xy(lat, lon)
    assert math.hypot(x, y) == pytest.approx(vincenty_m(lat0, lon0, lat, lon), abs=0.001)
    if abs(math.cos(bearing)) > 0.1:
        assert math.copysign(1, y) == math.copysign(1, math.cos(bearing))  # north is +y
    if abs(math.sin(bearing)) > 0.1:
        assert math.copysign(1, x) == math.copysign(1, math.sin(bearing))  # east is +x


def test_projection_origin_and_antimeridian():
    assert LocalProjection(10.0, 20.0).to_xy(10.0, 20.0) == (0.0, 0.0)
    x, _ = LocalProjection(0.0, 179.9999).to_xy(0.0, -179.9999)
    assert x == pytest.approx(vincenty_m(0.0, 179.9999, 0.0, -179.9999), abs=0.001)
    with pytest.raises(ValueError, match="origin"):
        LocalProjection(95.0, 0.0)


def test_configuration():
    gps = Gps.from_config(SimpleNamespace(GPS_SERIAL="/dev/ttyAMA1", GPS_SERIAL_BAUDRATE=9600))
    assert (gps.port.port, gps.port.baudrate) == ("/dev/ttyAMA1", 9600)
    assert gps.run() == (None, None, None, None, None)
    with pytest.raises(ValueError, match="use"):
        Gps("/dev/null", use=("VTG",))


# ------------------------------------------------------------------------------------- with the model
class Until:
    """Runs ``action`` once ``cond()`` holds, then stops the vehicle ``seconds`` later."""

    def __init__(self, vehicle, cond, seconds, action=None):
        self.vehicle, self.cond, self.seconds, self.action, self.t0 = vehicle, cond, seconds, action, None

    def run(self):
        now = get_clock().now()
        if self.t0 is None and self.cond():
            self.t0 = now
            if self.action is not None:
                self.action()
        if self.t0 is not None and now - self.t0 >= self.seconds - 1e-9:
            self.vehicle.stop()


def fix_time(peer: NmeaPeer, lat: float, lon: float) -> float:
    """Loop time of the epoch the model sent (lat, lon) in (NMEA keeps 1e-6 minute, under 2e-8 degree)."""
    return next(t for t, la, lo in reversed(peer.fixes) if abs(la - lat) < 1e-7 and abs(lo - lon) < 1e-7)


def truth_xy(peer: NmeaPeer, t_origin: float, t: float) -> tuple[float, float]:
    """Metres the model's antenna moved from ``t_origin`` to ``t``, from its own metric track (no projection)."""
    e0, n0 = peer.offset_m(t_origin - peer.t_start)
    e1, n1 = peer.offset_m(t - peer.t_start)
    return e1 - e0, n1 - n0


OUTPUTS = ["gps/latitude", "gps/longitude", "pos/x", "pos/y", "gps/timestamp"]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_positions_follow_the_moving_antenna():
    with NmeaPeer(velocity=(2.0, -1.0), rate_hz=10, origin=(48.1173, 11.5167)) as peer:
        gps = Gps(peer.path)
        v = Vehicle()
        v.add(gps, outputs=OUTPUTS)
        v.add(Until(v, lambda: gps.fix is not None, 3.0))
        await v.run(rate_hz=20, duration=600)
        lat, lon, x, y, ts = (v.mem[k] for k in OUTPUTS)
        assert gps.projection is not None
        t_origin = fix_time(peer, gps.projection.lat0, gps.projection.lon0)  # the first fix the part read
        tx, ty = truth_xy(peer, t_origin, fix_time(peer, lat, lon))
        assert x == pytest.approx(tx, abs=0.01) and y == pytest.approx(ty, abs=0.01)
        assert x > 5.0 and y < -2.5  # about 3 s at (2, -1) m/s
        assert ts <= get_clock().now()
        assert gps.parser.dropped == 0 and gps.parser.accepted >= 2 * 29


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_corrupt_sentences_are_counted_and_skipped():
    with NmeaPeer(velocity=(1.0, 0.0), rate_hz=10) as peer:
        gps = Gps(peer.path)
        v = Vehicle()

        def corrupt():  # the next sentence is a GGA (both of an epoch are sent together)
            for kind in ("no_fix", "void", "checksum", "truncated", "garbage"):
                peer.corrupt_next(kind)

        v.add(gps, outputs=OUTPUTS)
        v.add(Until(v, lambda: gps.fix is not None, 2.0, corrupt))
        await v.run(rate_hz=20, duration=600)
        assert gps.parser.counts == {
            "no_start": 1,
            "truncated": 1,
            "bad_checksum": 1,
            "malformed": 0,
            "void": 1,
            "no_fix": 1,
            "unsupported": 0,
        }
        assert v.mem["pos/x"] > 1.5  # positions kept coming


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_unplug_and_replug_keeps_the_origin():
    with NmeaPeer(velocity=(0.0, 1.5), rate_hz=5) as peer:
        gps = Gps(peer.path)
        gps.port.backoff_initial_s = 0.05
        loop = asyncio.get_running_loop()
        v = Vehicle()
        v.add(gps, outputs=OUTPUTS)

        def unplug_for_half_a_second():
            peer.unplug()
            loop.call_later(0.5, peer.plug)

        v.add(Until(v, lambda: gps.fix is not None, math.inf, unplug_for_half_a_second))
        reconnected = Until(v, lambda: gps.port.connects == 2 and gps.latest.sample.timestamp > loop.time() - 0.3, 1.0)
        v.add(reconnected)
        await v.run(rate_hz=20, duration=600)
        assert (gps.port.disconnects, gps.port.connects) == (1, 2)
        origin = gps.projection
        assert origin is not None
        lat, lon, x, y = (v.mem[k] for k in OUTPUTS[:4])
        t_origin = fix_time(peer, origin.lat0, origin.lon0)
        assert t_origin < 0.5  # the origin is still the first fix, from before the unplug
        tx, ty = truth_xy(peer, t_origin, fix_time(peer, lat, lon))
        assert (x, y) == (pytest.approx(tx, abs=0.01), pytest.approx(ty, abs=0.01))
        assert y > 2.0


@pytest.mark.realtime
def test_real_loop_smoke():
    """The same part on the real asyncio loop: a fix within a few hundred ms."""

    async def body():
        with NmeaPeer(rate_hz=20) as peer:
            gps = Gps(peer.path)
            task = asyncio.create_task(gps.update())
            deadline = time.monotonic() + 1.0
            while gps.fix is None and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            assert gps.run()[2:4] == (0.0, 0.0)
            await gps.shutdown()
            await asyncio.wait_for(task, 1)

    with asyncio.Runner(loop_factory=asyncio.SelectorEventLoop) as runner:
        runner.run(body())
