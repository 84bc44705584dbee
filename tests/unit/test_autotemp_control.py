"""The controller [autotemp] and the bake drive: which source, which
profile, when the slicer's M104 is overridden, and when it stands down."""

from __future__ import annotations

import pytest

from flowloop.control.autotemp import (
    DEFAULT_READ_AHEAD_S,
    DONE_AFTER_S,
    FLOW_MARGIN,
    GRID_S,
    LOOKAHEAD_WINDOW_S,
    MAX_HOLD_S,
    Autotemp,
    TemperaturePlan,
    hold_s,
)
from flowloop.errors import FlowloopError
from flowloop.host.klipper_config import HOST_BUFFER_TIME_S, host_facts
from flowloop.material.profile import profile_from_dict, temp_for_flow
from tests.samples import make

PROFILE = profile_from_dict(make())


def active(**kw):
    a = Autotemp(**kw)
    a.set_profile(PROFILE, 0.5)
    return a


def test_without_a_profile_it_stays_off_and_says_why():
    a = Autotemp()
    a.announce(0.0, 5.0, 15.0, 2.0)
    assert a.target_at(10.0) is None
    assert not a.overrides_m104()
    assert a.status["active"] is False
    assert "no active profile" in a.status["why"]


def test_annotations_set_the_source_targets_and_the_m104_override():
    a = active()
    assert not a.overrides_m104()           # start G-code: M104/M109 obeyed
    a.announce(0.0, 12.0, 15.0, 5.0)
    assert a.overrides_m104()
    s = a.status
    assert s["source"] == "annotation" and s["working_point"] == 0.5
    assert s["profile"] == PROFILE.name
    # the need: the announced flow's, FLOW_MARGIN higher
    need = temp_for_flow(PROFILE, 12.0 * (1 + FLOW_MARGIN), 0.5)
    assert need > temp_for_flow(PROFILE, 12.0, 0.5) > PROFILE.bounds.min_temp_c
    # during the window the target is the need (a steady state), the
    # targets set as the print goes (the model runs on them)
    for k in range(160):
        a.target_at(k * 0.1)
    assert a.target_at(16.0) == pytest.approx(need, abs=0.01)
    assert a.status["target"] == pytest.approx(need, abs=0.01)
    assert a.status["planned_flow"] == 12.0
    # moves do not replace annotations
    a.on_move(1.0, 20.0, 5.0)
    assert a.status["source"] == "annotation"


def test_without_annotations_moves_make_reactive_windows():
    a = active()
    a.on_move(0.0, 14.0, LOOKAHEAD_WINDOW_S / 2)
    assert a.status["source"] is None        # not a full window yet
    a.on_move(0.5, 3.0, LOOKAHEAD_WINDOW_S / 2)
    assert a.status["source"] == "lookahead"
    assert "reactive" in a.status["why"]
    # the window's peak, not its last move, sets the need
    assert temp_for_flow(PROFILE, 3.0, 0.5) < temp_for_flow(PROFILE, 14.0, 0.5)
    assert a.target_at(0.0) >= temp_for_flow(PROFILE, 14.0, 0.5)


def test_a_reactive_window_covers_the_hosts_read_ahead():
    """The moves gathered are still in Klipper's lookahead queue: they run
    up to the host's read-ahead after they are queued, so the window lasts
    that much longer (without it, the klippy test's reactive print lost
    more filament than the file's own temperatures: the targets fell back
    before the moves ran)."""
    # before the host is known: Klipper's (the one number, kept equal)
    assert DEFAULT_READ_AHEAD_S == HOST_BUFFER_TIME_S["Klipper"]
    for host, read_ahead in ((None, 1.0), (host_facts(True, "pid"), 2.0)):
        a = active()
        if host is not None:
            a.set_host(host)
        a.on_move(10.0, 14.0, LOOKAHEAD_WINDOW_S)
        (window,) = a.plan.windows
        assert window.start_s == 10.0
        assert window.end_s == pytest.approx(10.0 + LOOKAHEAD_WINDOW_S + read_ahead)


def test_the_model_starts_where_the_heater_was_set():
    """At the first flush the heater is at its target (the start's M109
    waited for it): a window 3 s ahead that needs that temperature needs no
    push; from the profile's minimum it needs the full target."""
    need = temp_for_flow(PROFILE, 12.0 * (1 + FLOW_MARGIN), 0.5)
    targets = {}
    for heater_c in (round(need + 0.5), PROFILE.bounds.min_temp_c):
        a = active()
        a.announce(0.0, 12.0, 3.0, 10.0)
        targets[heater_c] = a.on_flush(0.0, heater_c)
    hot, cold = targets.values()
    assert hot is None or hot <= need + 1.0       # None: the heater's target
    assert cold == PROFILE.bounds.max_temp_c


def test_the_model_starts_no_hotter_than_the_heater_reads():
    """A start that did not wait (M104, not M109): the heater reads 30 C
    under its target when autotemp takes over. Believed at its target, the
    model plans no push for a window 3 s ahead at that target; from the
    reading it heats at the most it may. A reading above the target is not
    taken (the model would only plan less heat)."""
    need = temp_for_flow(PROFILE, 12.0 * (1 + FLOW_MARGIN), 0.5)
    heater_c = round(need + 0.5)
    targets = []
    for nozzle_c in (None, heater_c - 30.0, heater_c + 20.0, float("nan")):
        a = active()
        a.announce(0.0, 12.0, 3.0, 10.0)
        targets.append(a.on_flush(0.0, heater_c, nozzle_c=nozzle_c))
    believed, cooler, hotter, unread = targets
    assert believed is None or believed <= need + 1.0
    assert cooler == PROFILE.bounds.max_temp_c
    assert hotter == believed and unread == believed


def test_a_heater_set_below_the_profiles_minimum_is_not_believed_hotter():
    """M109 S200 before a profile whose minimum is 210: the model starts at
    200, so the first window gets the heat it needs from there (clamped up
    to the minimum, the model believed the nozzle 10 C hotter and planned
    the same as from 210). The target itself stays within the limits."""
    low = PROFILE.bounds.min_temp_c
    targets = {}
    for heater_c in (low - 10.0, low):
        a = active()
        a.announce(0.0, 2.0, 2.0, 10.0)   # a small flow: the need sits near low
        targets[heater_c] = a.on_flush(0.0, heater_c)
    from_below, from_low = targets[low - 10.0], targets[low]
    assert from_below is not None
    assert from_below > (low if from_low is None else from_low)
    assert low <= from_below <= PROFILE.bounds.max_temp_c


def test_after_the_last_window_it_stands_down():
    a = active()
    a.announce(0.0, 6.0, 2.0, 3.0)
    assert a.target_at(4.0) is not None
    assert a.target_at(5.0 + DONE_AFTER_S + 0.1) is None
    assert not a.overrides_m104() and a.status["source"] is None


def test_stop_forgets_the_plan_and_disabled_plans_nothing():
    a = active()
    a.announce(0.0, 6.0, 2.0, 3.0)
    a.stop()
    assert a.target_at(3.0) is None and not a.overrides_m104()
    a.announce(0.0, 6.0, 2.0, 3.0)
    a.set_enabled(False)
    assert a.target_at(3.0) is None and not a.overrides_m104()
    assert "disabled" in a.status["why"]


def test_a_working_point_of_its_own_changes_the_line():
    a = active()
    a.announce(0.0, 12.0, 15.0, 5.0)
    before = a.target_at(16.0)
    a.set_working_point(1.0, 0.0)
    assert a.status["working_point"] == 1.0
    assert a.target_at(16.0) == pytest.approx(
        temp_for_flow(PROFILE, 12.0 * (1 + FLOW_MARGIN), 1.0), abs=0.01)
    assert a.target_at(16.0) != before
    with pytest.raises(FlowloopError):
        a.set_working_point(1.5)
    assert a.status["working_point"] == 1.0


def test_the_heater_max_temp_caps_targets():
    a = Autotemp(heater_max_temp_c=PROFILE.bounds.min_temp_c + 10)
    a.set_profile(PROFILE, 0.5)
    a.announce(0.0, 100.0, 15.0, 5.0)
    assert a.target_at(16.0) == PROFILE.bounds.min_temp_c + 10
    assert a.status["capped_windows"] == 1


# --- at each flush: what [autotemp] sets on the heater -------------------------

def test_a_target_holds_until_the_next_flush_within_a_grid_step_and_a_second():
    assert hold_s(None, 7.0) == GRID_S               # the first flush
    assert hold_s(7.0, 7.35) == pytest.approx(0.35)  # the gap since the last
    assert hold_s(7.0, 7.01) == GRID_S               # never below a grid step
    assert hold_s(7.0, 60.0) == MAX_HOLD_S           # a pause says nothing


def test_a_flush_looks_ahead_over_the_gap_since_the_last_one():
    # a rise 0.6 s after a flush: seen over a 1 s hold, not over one grid step
    a, b = active(), active()
    for ctl in (a, b):
        ctl.announce(0.0, 1.0, 0.0, 30.0)
        ctl.announce(0.0, 10.0, 10.6 + ctl.params.dead_time_s, 5.0)
    for k in range(91):                # flushes every 0.1 s up to 9 s
        a.on_flush(k * 0.1, 200.0)
        b.on_flush(k * 0.1, 200.0)
    for k in range(91, 100):           # b flushes on to 9.9 s, a waits
        b.on_flush(k * 0.1, 200.0)
    assert a.on_flush(10.0, 200.0) > b.on_flush(10.0, 200.0)


def test_a_heater_turned_off_while_it_plans_makes_it_stand_down():
    a = active()
    a.announce(0.0, 12.0, 1.0, 5.0)
    target = a.on_flush(1.0, 200.0)
    assert target is not None and a.overrides_m104()
    assert a.on_flush(1.1, 0.0) is None              # never turns a heater on
    assert a.status["source"] is None and not a.overrides_m104()
    assert a.on_flush(1.2, 0.0) is None


def test_a_tool_that_does_not_print_keeps_its_users_target():
    a = active()
    a.announce(0.0, 12.0, 1.0, 5.0)
    assert a.on_flush(1.0, 180.0, printing=False) is None
    assert a.last_flush_s == 1.0                     # the hold still follows


def test_a_target_the_heater_already_has_is_not_set_again():
    a = active()
    a.announce(0.0, 12.0, 1.0, 5.0)
    target = a.on_flush(2.0, 0.5)
    assert target is not None
    assert a.on_flush(2.1, target) is None


def test_no_target_leaves_the_heaters_own_limits():
    a = active()
    a.set_heater(PROFILE.bounds.min_temp_c + 5, PROFILE.bounds.min_temp_c + 20)
    a.announce(0.0, 0.1, 1.0, 5.0)                   # needs the profile's min
    held = PROFILE.bounds.min_temp_c + 5.5           # the start's M109
    assert a.on_flush(2.0, held) == PROFILE.bounds.min_temp_c + 5
    a.announce(2.0, 100.0, 1.0, 5.0)                 # beyond the heater
    assert a.on_flush(4.0, held) == PROFILE.bounds.min_temp_c + 20
    assert a.status["min_temp"] == PROFILE.bounds.min_temp_c + 5
    b = active()
    b.set_heater(255.0, 250.0)   # nothing left between them: off, saying why
    assert b.plan is None and "heater's min_temp 255" in b.status["why"]


def test_a_new_working_point_keeps_the_windows_announced():
    a = active()
    a.announce(0.0, 12.0, 15.0, 5.0)
    windows = list(a.plan.windows)
    a.set_working_point(1.0, 0.0)
    assert a.plan.windows == windows
    plan = a.plan
    assert isinstance(plan, TemperaturePlan)
    plan.set_windows([], 0.0)
    assert plan.windows == [] and plan.nozzle_c(16.0) == plan.limits.min_temp_c
