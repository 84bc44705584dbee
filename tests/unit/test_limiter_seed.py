"""The grip model seeded with this hotend's melt ratio from its earlier
prints (nozzle health's newest estimate, sent with an activation): issue
41's carry-over from one print to the next."""

from __future__ import annotations

import math

import pytest

from flowloop.control import nozzle_health as nh
from flowloop.control.grip_model import CLIMB_FROM, CapacityLine
from flowloop.control.limiter import (
    CONFIRM_SEED_S,
    SEED_PROBE,
    FlowLimiter,
    LimiterSettings,
)
from flowloop.errors import FlowloopError
from flowloop.material.profile import profile_line
from flowloop.window import JUDGED, Window
from tests.nozzle_prints import PROFILE as NH_PROFILE
from tests.nozzle_prints import simulate_print
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


def seeded_limiter(melt_ratio, climb_from=CLIMB_FROM):
    lim = FlowLimiter(LimiterSettings(mode="predictive", climb_from=climb_from),
                      AREA)
    lim.set_profile(PROFILE, 0.5, melt_ratio)
    lim.set_temperature(TEMP_C)
    return lim


def lost_over_first_moves(melt_ratio, melts_mm3_s, moves=20,
                          climb_from=CLIMB_FROM):
    """Filament (mm) a predictive limiter lets slip over its first moves at
    FAST, the hotend melting melts_mm3_s, each move one judged window."""
    lim = seeded_limiter(melt_ratio, climb_from)
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
    # a worn hotend: 69 % of what the profile's seed says it melts, seeded
    # with 0.7 (a model's belief sits a little above the hotend: a window
    # that slips under 2 % counts as kept up), so it starts at 0.714
    # (SEED_PROBE): its first windows slip 3 %, not 31 % (a fresh model
    # starting at the profile's line) or 10 % (one climbing from CLIMB_FROM)
    melts = 0.69 * profile_capacity()
    fresh, _ = lost_over_first_moves(None, melts, climb_from=1.0)
    climbing, _ = lost_over_first_moves(None, melts)
    carried, status = lost_over_first_moves(0.7, melts)
    assert fresh > 0.2            # the fresh model learns by slipping
    assert carried < 0.5 * fresh  # 0.085 against 0.31 mm
    assert carried < climbing < 0.5 * fresh    # 0.085 < 0.11 < 0.16 mm
    assert status["seed_melt_ratio"] == 0.7
    # the status says the ratio it was seeded with and what it believes
    assert status["caps"]["model"] == pytest.approx(melts, rel=0.03)


SEEDED_07 = 0.7 * (1.0 + SEED_PROBE)    # where a seed of 0.7 starts


def capped_seconds(moves):
    """Print time of `moves` of FAST capped where a seed of 0.7 starts."""
    speed = SEEDED_07 * profile_capacity() / FAST.flow_mm3_s(1.0, AREA)
    return moves * FAST.duration_s(speed)


@pytest.mark.parametrize("melts", [1.0, 0.9])
def test_a_seed_too_low_is_dropped_unconfirmed_and_the_model_starts_afresh(
        melts):
    # a new nozzle after a worn one: seeded at 0.7 on a hotend that melts
    # what the profile says (or 0.9 of it). Capped at the seed it never
    # slips, so its windows never show it melts more: once moves ran
    # CONFIRM_SEED_S under that cap with nothing learned, the seed is
    # dropped and the model starts from the profile's line
    moves = 1
    while capped_seconds(moves) < CONFIRM_SEED_S:
        moves += 1
    lost, status = lost_over_first_moves(0.7, melts * profile_capacity(),
                                         moves=moves - 1)
    assert lost == 0.0 and status["seed_melt_ratio"] == 0.7
    assert status["caps"]["model"] == pytest.approx(
        SEEDED_07 * profile_capacity(), rel=1e-3)
    lost, status = lost_over_first_moves(0.7, melts * profile_capacity(),
                                         moves=moves + 200)
    assert status["seed_melt_ratio"] is None
    assert status["dropped_melt_ratio"] == 0.7
    # from the profile's line: kept up at 1.0, learned 0.9 by slipping
    assert status["caps"]["model"] == pytest.approx(melts * profile_capacity(),
                                                    rel=0.03)


def test_a_seed_confirmed_by_a_window_is_kept():
    # seeded right (0.7 on a hotend melting 0.7), the first slips teach the
    # model: the seed stays however long the print runs
    lost, status = lost_over_first_moves(0.7, 0.68 * profile_capacity(),
                                         moves=2000)
    assert status["seed_melt_ratio"] == 0.7
    assert status["dropped_melt_ratio"] is None


def test_windows_that_keep_up_above_a_low_seed_raise_it():
    # what the model sees while another cap is in force or the limiter is
    # off: windows that kept up above its line
    lim = seeded_limiter(0.6)
    seed_cap = lim.status()["caps"]["model"]
    assert seed_cap == pytest.approx(0.6 * (1.0 + SEED_PROBE)
                                     * profile_capacity(), rel=1e-3)
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


@pytest.mark.parametrize("said, kept", [(0.8, 0.8), (1, 1.0), (math.nan, None),
                                        (math.inf, None), ("0.8", None),
                                        (True, None), (None, None)])
def test_what_klippy_says_its_model_believes_is_kept_beside_the_estimate(said,
                                                                         kept):
    # (Moonraker stores it with the job: only a finite number, and a bad
    # one never costs the job's estimate)
    evidence = nh.evidence_of(simulate_print(0.8, seed=1), NH_PROFILE)
    found = nh.estimate(evidence, said)
    assert found.model_ratio == kept
    assert found.known and found.ratio == nh.estimate(evidence).ratio
    assert nh.PrintEstimate.from_dict(found.to_dict()).model_ratio == kept
