"""The grip model seeded with this hotend's melt ratio from its earlier
prints (nozzle health's newest estimate, sent with an activation): issue
41's carry-over from one print to the next."""

from __future__ import annotations

import math

import pytest

from flowloop.control import nozzle_health as nh
from flowloop.control.grip_model import CapacityLine
from flowloop.control.limiter import FlowLimiter, LimiterSettings
from flowloop.errors import FlowloopError
from flowloop.material.profile import profile_line
from flowloop.window import JUDGED, Window
from tests.unit.test_limiter_bad_input import (
    AREA,
    FAST,
    PIECES,
    PROFILE,
    TEMP_C,
    profile_capacity,
)

LINE = profile_line(PROFILE, 0.5)


def test_the_seed_is_the_profile_line_times_the_ratio_at_every_temperature():
    plain = CapacityLine.from_profile_line(LINE, 0.9, 210.0)
    seeded = CapacityLine.from_profile_line(LINE, 0.9, 210.0, 0.8)
    for temp_c in (190.0, 210.0, 240.0):
        assert seeded.at(temp_c) == pytest.approx(0.8 * plain.at(temp_c))


def seeded_limiter(melt_ratio):
    lim = FlowLimiter(LimiterSettings(mode="predictive"), AREA)
    lim.set_profile(PROFILE, 0.5, melt_ratio)
    lim.set_temperature(TEMP_C)
    return lim


def lost_over_first_moves(melt_ratio, melts_mm3_s, moves=20):
    """Filament (mm) a predictive limiter lets slip over its first moves at
    FAST, the hotend melting melts_mm3_s, each move one judged window."""
    lim = seeded_limiter(melt_ratio)
    lost = 0.0
    for _ in range(moves):
        speed = lim.limit(FAST, 200.0)
        flow = FAST.flow_mm3_s(speed, AREA)
        grip = min(1.0, melts_mm3_s / flow)
        commanded = 0.5    # mm of filament per window
        lost += (1.0 - grip) * commanded
        lim.on_window(Window(0.0, commanded * AREA / flow, commanded,
                             grip * commanded, grip, JUDGED, temp_c=TEMP_C,
                             commanded_flows=(flow,) * PIECES))
    return lost, lim.status()


def test_a_limiter_seeded_from_the_last_print_does_not_slip_at_its_start():
    # a worn hotend: 70 % of what the profile's seed says it melts
    melts = 0.7 * profile_capacity()
    fresh, _ = lost_over_first_moves(None, melts)
    carried, status = lost_over_first_moves(0.7, melts)
    assert fresh > 0.2            # the fresh model learns by slipping
    assert carried < 0.05 * fresh
    assert status["seed_melt_ratio"] == 0.7
    # the status says the ratio it was seeded with and what it believes
    assert status["caps"]["model"] == pytest.approx(melts, rel=0.03)


def test_a_seed_too_low_stays_low_in_closed_loop_and_says_so():
    # a new nozzle after a worn one: seeded at 0.7 on a hotend that melts
    # what the profile says. Capped at the seed it never slips, so nothing
    # shows it more (as with a profile 30 % low, test_limiter_bad_input):
    # slower than it could be, never faster than asked, and said
    lost, status = lost_over_first_moves(0.7, profile_capacity(), moves=200)
    assert lost == 0.0
    assert status["seed_melt_ratio"] == 0.7 and status["reason"] == "model"
    assert status["caps"]["model"] == pytest.approx(0.7 * profile_capacity(),
                                                    rel=1e-3)
    # forgotten (its history deleted: an activation without a ratio), the
    # model starts from the profile's line again
    assert seeded_limiter(None).status()["caps"]["model"] == pytest.approx(
        profile_capacity(), rel=1e-3)


def test_windows_that_keep_up_above_a_low_seed_raise_it():
    # what the model sees while another cap is in force or the limiter is
    # off: windows that kept up above its line
    lim = seeded_limiter(0.6)
    seed_cap = lim.status()["caps"]["model"]
    assert seed_cap == pytest.approx(0.6 * profile_capacity(), rel=1e-3)
    flow = 0.95 * profile_capacity()
    for _ in range(10):
        lim.on_window(Window(0.0, 1.0, flow / AREA, flow / AREA, 1.0, JUDGED,
                             temp_c=TEMP_C, commanded_flows=(flow,) * PIECES))
    assert lim.status()["caps"]["model"] > 0.9 * profile_capacity()


@pytest.mark.parametrize("bad", [math.nan, math.inf, 0.1, 1.6, -1.0, "abc",
                                 True, [0.8]])
def test_a_bad_melt_ratio_is_one_line_and_changes_nothing(bad):
    lim = seeded_limiter(0.8)
    before = lim.status()
    with pytest.raises(FlowloopError) as e:
        lim.set_profile(PROFILE, 0.5, bad)
    assert str(e.value).startswith("melt_ratio: got ") and "\n" not in str(e.value)
    assert lim.status() is before and lim.seed_melt_ratio == 0.8


def test_a_ratio_given_as_text_reads_as_its_number():
    assert seeded_limiter("0.85").status()["seed_melt_ratio"] == 0.85


def test_the_newest_ratio_is_the_newest_print_that_gave_one():
    def est(ratio, reason=""):
        return nh.PrintEstimate("p", ratio=ratio, reason=reason)
    assert nh.newest_ratio([est(0.9), est(0.8), est(None, "no windows"),
                            est(0.7, "standard error too large")]) == 0.8
    # a stored ratio no print can give is never sent
    assert nh.newest_ratio([est(0.9), est(2.0)]) == 0.9
    assert nh.newest_ratio([]) is None
    assert nh.newest_ratio([est(None, "no profile")]) is None
