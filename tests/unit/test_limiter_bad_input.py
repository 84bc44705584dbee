"""The limiter on issue 41's bad input, in a closed loop with a simulated
hotend: a profile far off the hotend, a sensor that reports noise only, a
grip that never drops, a print of short moves. Whatever it reads, it never
makes a move faster than the G-code asked, never stops one, and its status
says what it believes the hotend melts."""

from __future__ import annotations

import math
import random

import pytest

from flowloop.control.caps import move_shape
from flowloop.control.grip_model import CLIMB_FROM, SLIP_TOLERANCE
from flowloop.control.limiter import FlowLimiter, LimiterSettings
from flowloop.material.profile import profile_from_dict, profile_line
from flowloop.window import JUDGED, TOO_LITTLE_MOTION, Window
from tests.samples import make

AREA = 2.405
PROFILE = profile_from_dict(make())
TEMP_C = 210.0
# 0.05 mm of filament per mm at 200 mm/s: 24 mm^3/s, above what any of
# these hotends melts
FAST = move_shape([0, 0, 0, 0], [100, 0, 0, 5])
ASKED_MM_S = 200.0
# a 0.5 mm window of filament, in 50 ms pieces
PIECES = 10


def profile_capacity():
    """What the limiter's seed says the hotend melts at TEMP_C (the
    profile's capacity: where a first print's model climbs to)."""
    lim = FlowLimiter(LimiterSettings(mode="predictive", climb_from=1.0), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(TEMP_C)
    return lim.status()["caps"]["model"]


def print_moves(melts_mm3_s, grip_of=None, moves=200, judged=True):
    """Moves at FAST through a predictive limiter on PROFILE, the hotend
    melting melts_mm3_s; each move closes one window whose grip is what the
    hotend passed (or grip_of(true grip): what a bad sensor reads). The
    limiter's status and each move's (speed, floor): the floor is what
    min_speed_factor leaves of what the hard caps allow."""
    lim = FlowLimiter(LimiterSettings(mode="predictive"), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(TEMP_C)
    hard = min(c for c in (lim.status()["caps"]["temperature"],) if c)
    hard_speed = min(ASKED_MM_S, hard / FAST.flow_mm3_s(1.0, AREA))
    floor = lim.settings.min_speed_factor * hard_speed
    speeds = []
    for _ in range(moves):
        speed = lim.limit(FAST, ASKED_MM_S)
        speeds.append(speed)
        flow = FAST.flow_mm3_s(speed, AREA)
        grip = min(1.0, melts_mm3_s / flow)
        if grip_of is not None:
            grip = grip_of(grip)
        duration = 0.5 * AREA / flow
        commanded = flow * duration / AREA
        if judged:
            lim.on_window(Window(0.0, duration, commanded, grip * commanded,
                                 grip, JUDGED, temp_c=TEMP_C,
                                 commanded_flows=(flow,) * PIECES))
        else:
            lim.on_window(Window(0.0, duration, commanded, 0.0, None,
                                 TOO_LITTLE_MOTION, temp_c=TEMP_C))
    return lim.status(), speeds, floor


def believed(status):
    """What the status says the limiter believes the hotend melts at
    TEMP_C (the grip model's line)."""
    model = status["model"]
    return model["capacity_mm3_s"] + model["slope_mm3_s_per_c"] * (
        TEMP_C - model["ref_temp_c"])


def never_faster_never_stopped(speeds, floor):
    assert max(speeds) <= ASKED_MM_S
    assert min(speeds) >= floor * (1 - 1e-9) > 0.0


def test_a_profile_30_percent_high_is_learned_and_said():
    truth = profile_capacity() / 1.3
    status, speeds, floor = print_moves(truth)
    never_faster_never_stopped(speeds, floor)
    assert believed(status) == pytest.approx(truth, rel=0.03)
    # the last moves run at what the hotend melts, up to the slip a window
    # may show and still count as kept up (SLIP_TOLERANCE)
    assert FAST.flow_mm3_s(speeds[-1], AREA) <= truth / (1 - SLIP_TOLERANCE)


def test_a_profile_30_percent_low_is_safe_and_says_what_it_believes():
    # the hotend melts more than the profile says: capped at the profile's
    # capacity it never slips, so nothing shows it more; it stays slow, and
    # the status says the capacity it believes
    seed = profile_capacity()
    status, speeds, floor = print_moves(seed / 0.7)
    never_faster_never_stopped(speeds, floor)
    assert believed(status) == pytest.approx(seed, rel=1e-3)
    assert status["reason"] == "model"


def test_a_sensor_that_reports_noise_only_never_speeds_up_or_stops_a_move():
    rng = random.Random(41)
    status, speeds, floor = print_moves(
        profile_capacity(), grip_of=lambda _: rng.uniform(0.0, 2.0))
    never_faster_never_stopped(speeds, floor)
    assert math.isfinite(believed(status)) and status["model"]["windows"] > 0
    assert status["caps"]["model"] is not None


def test_a_grip_that_never_drops_never_lifts_a_move_above_the_profile_line():
    # a sensor stuck at grip 1: the model never lowers, and where it would
    # rise (a window that kept up above it) the temperature cap, the
    # profile's line, still holds
    status, speeds, floor = print_moves(1e9, grip_of=lambda _: 1.0)
    never_faster_never_stopped(speeds, floor)
    line = profile_line(PROFILE, 0.5).flow_mm3_s(TEMP_C)
    assert max(FAST.flow_mm3_s(s, AREA) for s in speeds) <= line * (1 + 1e-6)
    assert believed(status) >= profile_capacity()


def test_a_print_of_short_moves_keeps_the_seed_and_says_so():
    # no window is long enough to judge: nothing is learned, nothing raised;
    # the model stays where a first print's climb starts, and says so
    status, speeds, floor = print_moves(1.0, judged=False)
    never_faster_never_stopped(speeds, floor)
    assert status["model"]["windows"] == 0
    assert status["grip_windows"]["judged"] == 0
    assert believed(status) == pytest.approx(CLIMB_FROM * profile_capacity(),
                                             rel=1e-3)
    assert status["model"]["climb_ratio"] == pytest.approx(CLIMB_FROM, abs=1e-4)
