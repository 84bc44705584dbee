"""FlowLimiter: which cap acts in which mode, the floor of the grip caps,
sensor faults, and bad input that changes nothing."""

from __future__ import annotations

import pytest

from flowloop.control.caps import move_shape
from flowloop.control.grip_model import CLIMB_FROM
from flowloop.control.limiter import FlowLimiter, LimiterSettings, status_line
from flowloop.errors import FlowloopError
from flowloop.material.profile import (
    DEFAULT_WORKING_POINT,
    profile_from_dict,
    profile_line,
)
from flowloop.window import FAULT, JUDGED, TOO_LITTLE_MOTION, Window
from tests.samples import make

AREA = 2.405
PROFILE = profile_from_dict(make())
LINE = profile_line(PROFILE, 0.5)
# 0.05 mm of filament per mm at 200 mm/s: 24 mm^3/s
FAST = move_shape([0, 0, 0, 0], [100, 0, 0, 5])


def flow(speed):
    return FAST.flow_mm3_s(speed, AREA)


def window(duration_s, commanded_mm, grip, temp_c, flows=(), reason=None,
           fault=None):
    """A closed grip window as [flow_sensor] delivers it."""
    if reason is None:
        reason = TOO_LITTLE_MOTION if grip is None else JUDGED
    return Window(0.0, duration_s, commanded_mm,
                  0.0 if grip is None else grip * commanded_mm, grip, reason,
                  temp_c=temp_c, commanded_flows=tuple(flows), fault=fault)


def test_max_flow_alone_caps_without_sensor_or_profile():
    lim = FlowLimiter(LimiterSettings(max_flow_mm3_s=12.0), AREA)
    assert flow(lim.limit(FAST, 200.0)) == pytest.approx(12.0)
    s = lim.status()
    assert (s["cap"], s["reason"], s["slowed_moves"]) == (12.0, "max_flow", 1)
    assert s["slowed_time"] == pytest.approx(100 / (12 / (AREA * 0.05)) - 0.5,
                                             abs=1e-3)
    assert "no active profile" in s["why"]


def test_the_temperature_cap_follows_the_measured_temperature():
    lim = FlowLimiter(LimiterSettings(mode="temperature"), AREA)
    lim.set_profile(PROFILE, 0.5)
    assert lim.status()["cap"] is None  # no reading yet: off, and says so
    assert "no hotend temperature" in lim.status()["why"]
    for temp in (200.0, 215.0, 240.0):
        lim.set_temperature(temp)
        assert lim.status()["reason"] == "temperature"
        assert flow(lim.limit(FAST, 200.0)) == pytest.approx(
            LINE.flow_mm3_s(temp), rel=1e-3)


def test_above_the_profile_max_temp_the_line_is_not_trusted():
    lim = FlowLimiter(LimiterSettings(mode="temperature"), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(300.0)
    assert lim.status()["cap"] == pytest.approx(LINE.flow_mm3_s(260.0), abs=1e-3)


def test_a_cold_hotend_crawls_but_never_stops():
    lim = FlowLimiter(LimiterSettings(mode="temperature"), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(25.0)
    assert lim.status()["caps"]["temperature"] == 0.0
    assert 0 < lim.limit(FAST, 200.0) < 1.0


def test_static_mode_ignores_the_profile():
    lim = FlowLimiter(LimiterSettings(mode="static"), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(200.0)
    assert lim.limit(FAST, 200.0) == 200.0
    assert lim.status()["reason"] == "none"


def test_a_slip_caps_at_the_measured_flow_down_to_the_floor():
    lim = FlowLimiter(LimiterSettings(mode="reactive", min_speed_factor=0.5), AREA)
    # 1.25 mm in 0.1 s is 30 mm^3/s commanded; grip 0.6 melts 18
    lim.on_window(window(0.1, 1.25, 0.6, None))
    melted = 0.6 * AREA * 12.5
    s = lim.status()
    assert s["reason"] == "grip" and s["cap"] == pytest.approx(melted, abs=1e-3)
    assert flow(lim.limit(FAST, 200.0)) == pytest.approx(melted, abs=1e-3)
    # a move 4x as fast would need a quarter: it gets the floor, half its speed
    assert lim.limit(FAST, 800.0) == pytest.approx(400.0)
    lim.on_window(window(0.1, 1.25, 0.95, None))
    lim.on_window(window(0.1, 1.25, None, None))
    assert lim.status()["grip_windows"] == {"judged": 2, "below_min_grip": 1}


def test_the_grip_floor_is_a_share_of_what_the_hard_caps_leave():
    # an unretract (extrude only) asked at 40 mm/s: max_flow leaves it
    # 6 mm^3/s, a slip measured 3; the floor (half) is of those 6, not of 40
    lim = FlowLimiter(LimiterSettings(mode="reactive", max_flow_mm3_s=6.0,
                                      min_speed_factor=0.5), AREA)
    lim.on_window(window(0.5, 1.25, 0.5, None))         # 6.01 mm^3/s, grip 0.5
    melted = 0.5 * AREA * 1.25 / 0.5
    unretract = move_shape([0, 0, 0, 0], [0, 0, 0, 2.0])
    assert lim.status()["caps"]["grip"] == pytest.approx(melted, abs=1e-3)
    assert unretract.flow_mm3_s(lim.limit(unretract, 40.0), AREA) == \
        pytest.approx(melted, abs=1e-3)
    lim.on_window(window(0.5, 1.25, 0.1, None))         # a slip to 0.6: the floor
    assert unretract.flow_mm3_s(lim.limit(unretract, 40.0), AREA) == \
        pytest.approx(3.0, abs=1e-3)


def test_predictive_mode_caps_before_any_slip():
    lim = FlowLimiter(LimiterSettings(mode="predictive", min_grip=0.9), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(210.0)
    s = lim.status()
    # seeded from the profile's line, measured where grip fell to 0.9: the
    # slip starts at 0.9 of the line; a first print's model caps below
    # that, CLIMB_FROM of it, before any window (and climbs from there)
    assert s["reason"] == "model"
    assert s["caps"]["model"] == pytest.approx(
        CLIMB_FROM * 0.9 * s["caps"]["temperature"], rel=1e-3)
    assert s["model"]["climb_ratio"] == pytest.approx(CLIMB_FROM, abs=1e-4)
    no_climb = FlowLimiter(LimiterSettings(mode="predictive", min_grip=0.9,
                                           climb_from=1.0), AREA)
    no_climb.set_profile(PROFILE, 0.5)
    no_climb.set_temperature(210.0)
    t = no_climb.status()
    assert t["caps"]["model"] == pytest.approx(0.9 * t["caps"]["temperature"],
                                               rel=1e-3)
    assert t["model"]["climb_ratio"] is None
    # a hotend weaker than its profile: the model learns and caps lower
    weak = 0.6 * LINE.flow_mm3_s(210.0)
    for _ in range(30):
        lim.on_window(window(0.1, 1.25, weak / 30.0, 210.0))
    s = lim.status()
    assert s["reason"] in ("grip", "model")
    assert s["caps"]["model"] < 0.8 * s["caps"]["temperature"]
    assert s["model"]["windows"] == 30


def test_a_sensor_fault_freezes_the_grip_caps_and_says_so():
    lim = FlowLimiter(LimiterSettings(mode="predictive", max_flow_mm3_s=25.0), AREA)
    lim.on_window(window(0.1, 1.25, 0.5, None))
    capped = lim.status()["caps"]["grip"]
    assert lim.status()["reason"] == "grip"
    # samples that are all bad close no window: one of no filament names it
    lim.on_window(window(0.0, 0.0, None, None, fault="magnet"))
    s = lim.status()
    # never raised: the cap in force stays
    assert s["reason"] == "grip" and s["caps"]["grip"] == capped
    assert "sensor fault 'magnet': grip caps frozen" in s["why"]
    # the windows a faulted sensor closes neither lower nor recover it: the
    # fault reaches the caps as their reason, whatever else they carry
    lim.on_window(window(0.1, 1.25, None, None, reason=FAULT, fault="magnet"))
    lim.on_window(window(0.1, 1.25, 0.1, None, reason=FAULT, fault="magnet"))
    for _ in range(40):
        lim.on_window(window(1.0, 12.5, 1.0, None, reason=FAULT,
                             fault="magnet"))
    assert lim.status()["caps"]["grip"] == capped
    assert lim.status()["grip_windows"]["judged"] == 1
    assert "sensor fault 'magnet'" in lim.status()["why"]
    # cleared (a window of no filament says so): the rule goes on from
    # where it was
    lim.on_window(window(0.0, 0.0, None, None))
    assert "sensor fault" not in lim.status()["why"]
    for _ in range(40):
        lim.on_window(window(1.0, 12.5, 1.0, None))
    assert lim.status()["caps"]["grip"] is None


def test_disabled_caps_nothing():
    lim = FlowLimiter(LimiterSettings(max_flow_mm3_s=5.0), AREA)
    lim.configure(enabled=False)
    assert lim.limit(FAST, 200.0) == 200.0
    assert lim.status()["enabled"] is False and lim.status()["cap"] is None


@pytest.mark.parametrize("kw, message", [
    ({"max_flow_mm3_s": -3}, "MAX_FLOW must be above 0"),
    ({"max_flow_mm3_s": "x"}, "MAX_FLOW must be a number"),
    ({"mode": "fast"}, "mode must be one of static, temperature, reactive"),
    ({"enabled": False, "mode": "fast"}, "mode must be one of"),
])
def test_bad_input_changes_nothing(kw, message):
    lim = FlowLimiter(LimiterSettings(max_flow_mm3_s=10.0), AREA)
    before = lim.status()
    with pytest.raises(FlowloopError, match=message):
        lim.configure(**kw)
    assert lim.status() == before


@pytest.mark.parametrize("kw, message", [
    ({"min_grip": 0.0}, r"min_grip must be in \(0, 1\]"),
    ({"min_grip": 1.5}, r"min_grip must be in \(0, 1\]"),
    ({"min_speed_factor": 0.0}, r"min_speed_factor must be in \(0, 1\]"),
    ({"max_flow_mm3_s": 0.0}, "max_flow must be above 0"),
])
def test_bad_settings_are_refused(kw, message):
    with pytest.raises(FlowloopError, match=message):
        LimiterSettings(**kw)


def test_min_grip_defaults_to_the_profile_s():
    lim = FlowLimiter(LimiterSettings(), AREA)
    assert lim.min_grip == 0.9
    strict = profile_from_dict(make(provenance={"method": "manual",
                                                "min_grip": 0.95}))
    lim.set_profile(strict, 0.5)
    assert lim.min_grip == 0.95
    assert lim.status()["min_grip"] == 0.95


def test_the_status_is_plain_json_whatever_numbers_the_sensor_hands_over():
    import msgspec
    import numpy as np
    lim = FlowLimiter(LimiterSettings(max_flow_mm3_s=20.0), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(np.float64(212.0))
    lim.on_window(window(np.float64(0.1), np.float64(1.25), np.float64(0.5),
                  np.float64(212.0)))
    lim.limit(FAST, 200.0)
    msgspec.json.encode(lim.status())  # no numpy scalar anywhere
    assert type(lim.status()["grip_windows"]["below_min_grip"]) is int


def test_the_status_is_held_and_replaced_never_changed_in_place():
    # klippy's status poll keeps the dict get_status handed it and compares
    # the next one with it: a change made in place would never be reported
    lim = FlowLimiter(LimiterSettings(max_flow_mm3_s=12.0), AREA)
    held = lim.status()
    assert lim.status() is held  # reading builds nothing
    lim.limit(FAST, 200.0)       # slowed
    lim.on_window(window(0.1, 1.25, 0.5, 212.0))
    assert held["slowed_moves"] == 0 and held["grip_windows"]["judged"] == 0
    now = lim.status()
    assert now["slowed_moves"] == 1 and now["grip_windows"]["judged"] == 1
    lim.limit(move_shape([0, 0, 0, 0], [100, 0, 0, 0.5]), 200.0)  # under the cap
    assert lim.status() is now


def test_a_move_under_every_cap_keeps_its_speed_and_counts_nothing():
    lim = FlowLimiter(LimiterSettings(max_flow_mm3_s=flow(200.0)), AREA)
    assert lim.limit(FAST, 200.0) == 200.0   # exactly at the cap
    assert lim.limit(FAST, 199.0) == 199.0
    assert lim.limit(FAST, 201.0) < 201.0
    assert lim.status()["slowed_moves"] == 1


def test_the_working_point_without_an_activation_is_the_one_default(monkeypatch):
    # one source for the number: the limiter reads the profile module's
    import inspect

    import flowloop.control.limiter as L
    default = inspect.signature(L.FlowLimiter.set_profile).parameters[
        "working_point"].default
    assert default is DEFAULT_WORKING_POINT
    monkeypatch.setattr(L, "DEFAULT_WORKING_POINT", 0.25)
    assert L.FlowLimiter().working_point == 0.25


def test_a_climbing_model_tells_nozzle_health_no_ratio_until_a_slip_measures():
    # a first print: the model believes CLIMB_FROM of the profile (its cap),
    # but that is only a lower bound, so the next print is not seeded from it
    lim = FlowLimiter(LimiterSettings(mode="predictive", min_grip=0.9), AREA)
    lim.set_profile(PROFILE, 0.5)
    lim.set_temperature(210.0)
    assert lim.model_melt_ratio == pytest.approx(CLIMB_FROM, abs=1e-4)
    assert lim.measured_melt_ratio is None
    line = status_line("flowrate_limiter", lim.status())
    assert f"model climbing, at {CLIMB_FROM:.2f} of the profile's capacity" in line
    # a window that slipped beyond the noise band ends the climb: measured
    lim.on_window(window(0.1, 1.25, 0.8, 210.0))    # 30 mm^3/s asked
    assert lim.model.climb_ratio is None
    assert lim.measured_melt_ratio == lim.model_melt_ratio
    assert "climbing" not in status_line("flowrate_limiter", lim.status())


def test_the_query_line_says_the_caps_and_the_seed():
    lim = FlowLimiter(LimiterSettings(mode="predictive", min_grip=0.9,
                                      max_flow_mm3_s=12.0), AREA)
    lim.set_profile(PROFILE, 0.5, melt_ratio=0.8)
    line = status_line("flowrate_limiter", lim.status())
    assert line.startswith("flowrate_limiter: enabled, mode predictive, cap 12.00"
                           " mm^3/s (max_flow); caps: max_flow 12.00,")
    assert "; model seeded at melt ratio 0.80" in line
    assert "no hotend temperature" in line and "climbing" not in line


# 120 mm at 40 mm/s extruding: a 3 s infill line
LONG_LINE = move_shape([40, 100, 0, 0], [160, 100, 0, 8.7])


@pytest.mark.parametrize("mode", ["temperature", "reactive", "predictive"])
def test_a_long_line_is_queued_in_pieces_where_a_cap_follows_the_hotend(mode):
    lim = FlowLimiter(LimiterSettings(mode=mode), AREA)
    assert lim.pieces(LONG_LINE, 40.0) == 6
    assert lim.pieces(FAST, 200.0) == 1   # 0.5 s: within klippy's buffer


@pytest.mark.parametrize("settings, enabled", [
    (LimiterSettings(mode="static", max_flow_mm3_s=5.0), True),
    (LimiterSettings(max_flow_mm3_s=5.0), False),
])
def test_a_limiter_whose_caps_cannot_move_queues_moves_whole(settings, enabled):
    lim = FlowLimiter(settings, AREA)
    lim.configure(enabled=enabled)
    assert lim.pieces(LONG_LINE, 40.0) == 1

