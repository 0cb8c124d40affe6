"""NMEA parsing: known sentences decode exactly; every kind of bad line is counted by reason, never raised."""

from __future__ import annotations

import datetime as dt
import math

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from asyncdonkey.hw.nmea import REASONS, Gga, NmeaParser, Rmc, nmea_checksum, parse_latitude, parse_longitude
from asyncdonkey.testing.serial_peers import nmea_sentence

# Textbook sentences (the NMEA reference examples) and one from Donkeycar's gps.py comments.
GGA = "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"
RMC = "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A"
RMC_DK = "$GPRMC,003918.00,A,3806.92281,N,12235.64362,W,0.090,,060322,,,D*67"


def test_checksum_is_the_xor_of_the_bytes_between_dollar_and_star():
    assert nmea_checksum("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") == 0x47
    assert nmea_checksum(b"") == 0
    assert nmea_checksum("AB") == ord("A") ^ ord("B")


def test_gga_decodes_exactly():
    p = NmeaParser()
    fix = p.parse(GGA + "\r\n")
    assert isinstance(fix, Gga)
    assert fix.talker == "GP"
    assert fix.latitude == pytest.approx(48 + 7.038 / 60, abs=1e-12)
    assert fix.longitude == pytest.approx(11 + 31.000 / 60, abs=1e-12)
    assert (fix.quality, fix.satellites, fix.hdop, fix.altitude_m) == (1, 8, 0.9, 545.4)
    assert fix.utc_time == dt.time(12, 35, 19, tzinfo=dt.UTC)
    assert p.accepted == 1 and p.dropped == 0


def test_rmc_decodes_exactly_with_south_and_west_negative():
    p = NmeaParser()
    fix = p.parse(RMC)
    assert isinstance(fix, Rmc)
    assert (fix.speed_knots, fix.course_deg, fix.date) == (22.4, 84.4, dt.date(1994, 3, 23))
    dk = p.parse(RMC_DK)
    assert isinstance(dk, Rmc)
    assert dk.latitude == pytest.approx(38 + 6.92281 / 60, abs=1e-12)
    assert dk.longitude == pytest.approx(-(122 + 35.64362 / 60), abs=1e-12)
    assert dk.utc_time == dt.time(0, 39, 18, tzinfo=dt.UTC)
    assert dk.date == dt.date(2022, 3, 6)
    assert dk.course_deg is None
    south = p.parse(nmea_sentence("GNRMC,010203.50,A,3352.1280,S,15112.5600,E,0.0,,010124,,,A"))
    assert isinstance(south, Rmc) and south.talker == "GN"
    assert south.latitude == pytest.approx(-(33 + 52.128 / 60), abs=1e-12)
    assert south.utc_time == dt.time(1, 2, 3, 500000, tzinfo=dt.UTC)


def test_lower_case_checksum_digits_are_accepted():
    assert NmeaParser().parse(RMC[:-2] + "6a") is not None


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        (RMC[:-2] + "6B", "bad_checksum"),
        (GGA.replace("4807.038", "4807.039"), "bad_checksum"),
        (nmea_sentence("GPRMC,123519,V,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W"), "void"),
        (nmea_sentence("GPRMC,123519,A,4807.038,N,01131.000,E,0,0,230394,,,N"), "void"),
        (nmea_sentence("GPGGA,123519,,,,,0,00,99.9,,M,,M,,"), "no_fix"),
        (RMC[:30], "truncated"),
        (RMC[:-1], "truncated"),
        ("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A", "no_start"),
        ("", "no_start"),
        ("\x00\xff garbage", "no_start"),
        (nmea_sentence("GPRMC,123519,A,9507.038,N,01131.000,E,022.4,084.4,230394,003.1,W"), "malformed"),
        (nmea_sentence("GPRMC,123519,A,4867.038,N,01131.000,E,022.4,084.4,230394,003.1,W"), "malformed"),
        (nmea_sentence("GPRMC,123519,A,4807.038,X,01131.000,E,022.4,084.4,230394,003.1,W"), "malformed"),
        (nmea_sentence("GPRMC,123519,A,4807.038,N,01131.000,E,fast,084.4,230394,003.1,W"), "malformed"),
        (nmea_sentence("GPRMC,123519,A,4807.038,N"), "malformed"),
        (nmea_sentence("GPRMC,993519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W"), "malformed"),
        (nmea_sentence("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,320394,003.1,W"), "malformed"),
        (nmea_sentence("GPGGA,123519,4807.038,N,01131.000,E,x,08,0.9,545.4,M,46.9,M,,"), "malformed"),
        (RMC + "0", "malformed"),
        (nmea_sentence("GPGSV,3,1,11,03,03,111,00,04,15,270,00,06,01,010,00,13,06,292,00"), "unsupported"),
        (nmea_sentence("PUBX,00,081350.00"), "unsupported"),
    ],
)
def test_each_bad_line_is_dropped_and_counted_by_reason(line, reason):
    p = NmeaParser()
    assert p.parse(line) is None
    assert p.last_reason == reason
    assert p.counts == {r: int(r == reason) for r in REASONS}
    assert p.accepted == 0


def test_counts_accumulate_over_a_stream():
    p = NmeaParser()
    lines = [GGA, RMC, RMC[:-2] + "00", RMC[:20], "noise", GGA]
    fixes = [p.parse(x) for x in lines]
    assert [f is not None for f in fixes] == [True, True, False, False, False, True]
    assert p.accepted == 3
    assert (p.counts["bad_checksum"], p.counts["truncated"], p.counts["no_start"]) == (1, 1, 1)
    assert p.dropped == 3


def test_coordinate_helpers_raise_value_error_on_nonsense():
    assert parse_latitude("0000.000", "N") == 0.0
    assert parse_longitude("18000.000", "W") == -180.0
    for bad in ("", "12", "4807,038", "48a7.038", "-4807.038"):
        with pytest.raises(ValueError):
            parse_latitude(bad, "N")
    with pytest.raises(ValueError):
        parse_longitude("18000.001", "E")


# ------------------------------------------------------------------------------------------- properties
def _fmt(value: float, lat: bool) -> tuple[str, str]:
    hemi = ("N" if value >= 0 else "S") if lat else ("E" if value >= 0 else "W")
    value = abs(value)
    deg = int(value)
    minutes = (value - deg) * 60.0
    text = f"{minutes:010.7f}"
    if text.startswith("60"):
        deg, text = deg + 1, f"{0.0:010.7f}"
    return f"{deg:0{2 if lat else 3}d}{text}", hemi


@settings(max_examples=300, deadline=None)
@given(
    st.floats(min_value=-89.9, max_value=89.9, allow_nan=False),
    st.floats(min_value=-179.9, max_value=179.9, allow_nan=False),
    st.sampled_from(["GP", "GN", "GL", "GA", "BD"]),
)
def test_any_position_round_trips_through_rmc_and_gga(lat, lon, talker):
    la, ns = _fmt(lat, True)
    lo, ew = _fmt(lon, False)
    p = NmeaParser()
    rmc = p.parse(nmea_sentence(f"{talker}RMC,120000.00,A,{la},{ns},{lo},{ew},1.0,90.0,010124,,,A"))
    gga = p.parse(nmea_sentence(f"{talker}GGA,120000.00,{la},{ns},{lo},{ew},4,12,0.6,10.0,M,0.0,M,,"))
    for fix in (rmc, gga):
        assert fix is not None and fix.talker == talker
        assert math.isclose(fix.latitude, lat, abs_tol=1e-8)  # 7 decimals of minutes: < 2e-9 degrees
        assert math.isclose(fix.longitude, lon, abs_tol=1e-8)


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=120))
def test_arbitrary_text_never_raises_and_every_line_is_accounted_for(text):
    p = NmeaParser()
    out = p.parse(text)
    assert (out is not None) + sum(p.counts.values()) == 1


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=100))
def test_arbitrary_bytes_decoded_leniently_never_raise(data):
    p = NmeaParser()
    p.parse(data.decode("latin-1"))
    p.parse("$" + data.decode("latin-1"))
    assert sum(p.counts.values()) + p.accepted == 2


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_any_single_character_change_in_the_body_is_rejected(data):
    """XOR catches every single-byte error: a corrupted sentence never yields a position."""
    line = data.draw(st.sampled_from([GGA, RMC, RMC_DK]))
    star = line.rindex("*")
    i = data.draw(st.integers(min_value=1, max_value=star - 1))
    ch = data.draw(st.characters(min_codepoint=0x20, max_codepoint=0x7E))
    assume(ch != line[i] and ch != "*")
    corrupted = line[:i] + ch + line[i + 1 :]
    p = NmeaParser()
    assert p.parse(corrupted) is None
    assert p.last_reason in {"bad_checksum"}
