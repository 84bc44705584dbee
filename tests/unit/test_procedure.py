"""MEASURE_MATERIAL_PROFILE as a procedure (flowloop.material.procedure):
its actions carried out on the simulated twin (flowloop.sensor.twin, its
hotend the thermal model of flowloop.control.hotend, its grip windows from
the sensor's estimator), and each decision and way out on its own."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flowloop.control import watchdog
from flowloop.control.hotend import HotendModel, HotendParams
from flowloop.errors import FlowloopError
from flowloop.material import measure
from flowloop.material import procedure as proc
from flowloop.material.profile import (
    DEFAULT_MIN_GRIP,
    FlowLine,
    MeasuredPoint,
    profile_from_dict,
)
from flowloop.sensor.grip import DEFAULT_WINDOW_MM, GripEstimator
from flowloop.sensor.twin import SimulatedEms22, scaled_line
from flowloop.window import FAULT, JUDGED, Window
from tests.samples import TWIN_FLOW, TWIN_SLOPE, TWIN_TEMP, twin_known

pytestmark = pytest.mark.unit

# The twin melts this line at any working point (the klippy test's too)
SLOPE, TEMP, FLOW = TWIN_SLOPE, TWIN_TEMP, TWIN_FLOW
KNOWN = profile_from_dict(twin_known())
AREA = 2.405
HARDWARE = proc.Hardware(filament_area_mm2=AREA, nozzle_diameter_mm=0.4,
                         max_power=1.0, window_mm=DEFAULT_WINDOW_MM)
SETTINGS = proc.Settings(step_time_s=3.0, settle_time_s=5.0)
TWIN = HotendParams(max_power_w=40.0)


def make(temps=(200.0, 220.0, 240.0), powers=None, start_flow=4.0, step=0.25,
         max_flow=14.0, min_grip=0.9, base=KNOWN, settings=SETTINGS,
         hardware=HARDWARE, min_temp=None, max_temp=None):
    bounds = proc.bounds_for(base, min_temp, max_temp, 300.0)
    plan = measure.make_plan(temps, powers, start_flow, step, max_flow,
                             min_grip, bounds.min_temp_c, bounds.max_temp_c)
    _, rules = watchdog.for_measurement(bounds)
    return proc.Procedure("measured", plan, bounds, settings, base, hardware,
                          rules)


class Twin:
    """The procedure's actions done on the twin: the hotend model heats
    with its own controller or at a held power, the twin melts what the
    known line gives at the nozzle's temperature, the grip estimator closes
    windows from the filament that moved. Print time is the model's."""

    def __init__(self, temp_c=TEMP, sample_s=0.002):
        self.hotend = HotendModel(TWIN, temp_c=temp_c, target_c=temp_c)
        line = FlowLine(slope_mm3_s_per_c=SLOPE, temp_c=TEMP,
                        flow_mm3_s=FLOW).line()
        self.twin = SimulatedEms22(line, filament_area_mm2=AREA,
                                   hotend=self.hotend, noise_counts=0.0)
        self.grip = GripEstimator(filament_area_mm2=AREA)
        self.sample_s = sample_s
        self.time = 0.0
        self.filament = 0.0
        self.target = temp_c
        self.fault = None
        self.actions = []

    def run(self, procedure, until=None):
        """Answer every action until Done or Stop (or until(action))."""
        action = procedure.start()
        while not isinstance(action, (proc.Done, proc.Stop)):
            self.actions.append(action)
            if until is not None and until(action):
                return action
            action = procedure.send(self.answer(action, procedure))
        return action

    def answer(self, action, procedure):
        hotend = self.hotend
        if isinstance(action, proc.HeatTo):
            self.target = action.temp_c
        elif isinstance(action, proc.HoldPower):
            hotend.fixed_power_w = action.pwm * TWIN.max_power_w
            self.target = procedure.bounds.min_temp_c
        elif isinstance(action, proc.Release):
            hotend.fixed_power_w = None
        elif isinstance(action, proc.Dwell):
            self.time += action.seconds
            hotend.set_target(hotend.time_s, self.target)
            hotend.advance(self.time)
        elif isinstance(action, proc.Read):
            return proc.Reading(self.time, hotend.temp_c,
                                hotend.power_w / TWIN.max_power_w,
                                sensor_fault=self.fault)
        elif isinstance(action, proc.Extrude):
            return self.extrude(action, procedure)
        return None

    def extrude(self, action, procedure):
        start = self.time
        seconds = sum(action.moves_s)
        times = start + np.arange(1, round(seconds / self.sample_s) + 1) \
            * self.sample_s
        commanded = self.filament + action.speed_mm_s * (times - start)
        moved = self.twin.advance(times, commanded, self.target)
        for window in self.grip.add(times, moved, commanded,
                                    temp_c=self.hotend.temp_c):
            procedure.window(window)
        self.time, self.filament = float(times[-1]), float(commanded[-1])
        return proc.Extruded(start, self.time)


def said(twin):
    return [a.text for a in twin.actions if isinstance(a, proc.Say)]


def window(start, end, grip=1.0, flow=5.0, temp=210.0, mm=1.25,
           reason=JUDGED):
    return Window(start, end, mm, (grip or 0.0) * mm, grip, reason, flow, temp)


# --- on the twin -------------------------------------------------------------
def test_a_temps_run_on_the_twin_recovers_its_line():
    procedure = make()
    twin = Twin()
    done = twin.run(procedure)
    assert isinstance(done, proc.Done), done
    line = done.profile.lines.into_air.line()
    assert line.slope_mm3_s_per_c == pytest.approx(SLOPE, rel=0.05)
    assert line.flow_mm3_s(220.0) == pytest.approx(
        FLOW + SLOPE * 10.0, rel=0.03)
    assert [p.kind for p in done.points] == ["into_air"] * 3
    assert all(p.grip < 0.9 and 0 < p.heater_pwm < 255 for p in done.points)
    assert done.lines == tuple(done.fitted.lines())
    assert done.profile.provenance.source == "MEASURE_MATERIAL_PROFILE"
    assert done.profile.provenance.min_grip == 0.9
    # each level: heat, settle, hold, settle, ramp; then the heater back
    kinds = [type(a) for a in twin.actions if not isinstance(a, (
        proc.Say, proc.Read, proc.Dwell, proc.Extrude))]
    assert kinds == [proc.HeatTo, proc.HoldPower, proc.Release] * 3
    text = said(twin)
    assert text[0] == "level 1/3 (200 degC): heating to 200 degC"
    assert any(t.startswith("level 3/3 (240 degC): heater held at") for t in text)
    assert text[-1].startswith("level 3/3 (240 degC): limit ")
    # the progress the status shows
    assert procedure.progress == proc.Progress(
        levels=3, level=3, flow=procedure.progress.flow, points=done.points)


def test_a_powers_run_heats_where_each_power_holds_then_holds_it():
    procedure = make(temps=None, powers=(0.30, 0.36))
    twin = Twin()
    done = twin.run(procedure)
    assert isinstance(done, proc.Done), done
    assert [p.heater_pwm for p in done.points] == pytest.approx(
        [0.30 * 255, 0.36 * 255])
    holds = [a.pwm for a in twin.actions if isinstance(a, proc.HoldPower)]
    assert holds == [0.30, 0.36]
    heats = [a.temp_c for a in twin.actions if isinstance(a, proc.HeatTo)]
    assert heats[0] == 210.0     # the recommended temperature first
    idle = [TWIN.ambient_c + p * TWIN.max_power_w / TWIN.loss_w_per_c
            for p in (0.30, 0.36)]
    # the last heating before each hold lies within 2 degC of where its
    # power holds the idle nozzle (on the loss line through ambient)
    before_hold = []
    last = None
    for a in twin.actions:
        if isinstance(a, proc.HeatTo):
            last = a.temp_c
        elif isinstance(a, proc.HoldPower):
            before_hold.append(last)
    assert before_hold == pytest.approx(idle, abs=measure.POWER_LEVEL_BAND_C)
    assert "level 1/2 (power 30%): heating to 210 degC for the power" \
        " that holds it" in said(twin)


def test_without_start_flow_a_level_starts_near_its_expected_limit():
    procedure = make(temps=(200.0, 230.0), start_flow=None, step=0.5)
    twin = Twin()
    done = twin.run(procedure)
    assert isinstance(done, proc.Done), done
    first = next(a for a in twin.actions if isinstance(a, proc.Extrude))
    settled = [a for a in twin.actions if isinstance(a, proc.HoldPower)]
    assert settled
    # 80 % of what the base expects near 200 degC (4.8 mm^3/s)
    assert first.flow_mm3_s == pytest.approx(0.8 * 4.8, abs=0.1)


# --- the ways out ------------------------------------------------------------
def test_a_level_without_slip_stops_naming_max_flow():
    twin = Twin()
    stop = twin.run(make(temps=(200.0, 220.0), start_flow=2.0, step=0.25,
                         max_flow=2.5))
    assert stop == proc.Stop("level 1/2 (200 degC): grip stayed above 0.9 up"
                             " to MAX_FLOW 2.5 mm^3/s (raise MAX_FLOW)")


def test_a_cancel_stops_at_the_next_reading():
    procedure = make()
    twin = Twin()
    action = twin.run(procedure, until=lambda a: isinstance(a, proc.Extrude))
    procedure.cancel("cancelled (CANCEL_MATERIAL_PROFILE)")
    action = procedure.send(twin.answer(action, procedure))
    while not isinstance(action, proc.Stop):
        assert not isinstance(action, (proc.Extrude, proc.Done))
        action = procedure.send(twin.answer(action, procedure))
    assert action.reason == "cancelled (CANCEL_MATERIAL_PROFILE)"
    # and it stays the end
    assert procedure.send() is action


def test_a_sensor_fault_at_fixed_power_stops_the_level():
    procedure = make()
    twin = Twin()
    twin.run(procedure, until=lambda a: isinstance(a, proc.HoldPower))
    twin.fault = "missing"
    action = procedure.send(None)
    while not isinstance(action, proc.Stop):
        action = procedure.send(twin.answer(action, procedure))
    assert action.reason == watchdog.sensor_stop("missing")


def test_the_heaters_own_cut_and_the_trend_rule_stop_a_level():
    procedure = make()
    twin = Twin()
    twin.run(procedure, until=lambda a: isinstance(a, proc.Extrude))
    # the reading before the first step was read: a reading 12 degC above
    # where the level settled (and below the bounds' 250) ends it
    action = procedure.send(twin.answer(twin.actions[-1], procedure))
    assert isinstance(action, proc.Say)
    action = procedure.send()
    assert isinstance(action, proc.Read)
    stop = procedure.send(proc.Reading(twin.time, 212.5, 0.3))
    assert isinstance(stop, proc.Stop)
    assert "more than 10 degC above where it settled" in stop.reason, stop
    # and one that falls faster than a hotend cools (20 degC/s) too
    procedure = make()
    twin = Twin()
    twin.run(procedure, until=lambda a: isinstance(a, proc.Extrude))
    procedure.send(twin.answer(twin.actions[-1], procedure))
    action = procedure.send()                   # the reading after the step
    assert isinstance(action, proc.Read)
    read_s = twin.time
    action = procedure.send(proc.Reading(read_s, 200.0, 0.3))
    assert isinstance(action, proc.Extrude)     # the next step: one reading
    action = procedure.send(twin.answer(action, procedure))  # between two
    while not isinstance(action, proc.Read):
        action = procedure.send()
    stop = procedure.send(proc.Reading(read_s + 0.1, 198.0, 0.3))
    assert isinstance(stop, proc.Stop)
    assert "degC/s at fixed power" in stop.reason, stop
    procedure = make()
    Twin().run(procedure, until=lambda a: isinstance(a, proc.HoldPower))
    procedure.send()
    stop = procedure.send(proc.Reading(0.0, 200.0, 0.3,
                                       heater_stop="the host has not answered"))
    assert stop == proc.Stop("the host has not answered")


def test_a_temperature_that_does_not_settle_stops_the_run():
    procedure = make(settings=proc.Settings(step_time_s=3.0, settle_time_s=5.0,
                                            max_settle_time_s=30.0))
    action = procedure.start()
    time = 0.0
    while not isinstance(action, proc.Stop):
        if isinstance(action, proc.Read):
            # swinging 2 degC each second: never settles
            action = procedure.send(proc.Reading(time, 200.0 + 2 * (time % 2),
                                                 0.3))
        else:
            time += action.seconds if isinstance(action, proc.Dwell) else 0
            action = procedure.send()
    assert action.reason == ("the temperature did not settle within 30 s"
                             " (at 202.0 degC)")


def test_a_step_without_a_judged_window_runs_again_then_stops():
    procedure = make(settings=proc.Settings(step_time_s=3.0, settle_time_s=2.0))
    action = procedure.start()
    extrudes = []
    logged = []
    time = 0.0
    while not isinstance(action, proc.Stop):
        answer = None
        if isinstance(action, proc.Read):
            answer = proc.Reading(time, 200.0, 0.3)
        elif isinstance(action, proc.Dwell):
            time += action.seconds
        elif isinstance(action, proc.Extrude):
            extrudes.append(action)
            # only windows the step cannot judge (a retraction in each)
            procedure.window(window(time, time + 1.0, grip=None,
                                    reason="retraction"))
            answer = proc.Extruded(time, time + sum(action.moves_s))
            time += sum(action.moves_s)
        elif isinstance(action, proc.Log):
            logged.append(action.text)
        action = procedure.send(answer)
    assert len(extrudes) == proc.MAX_STEP_RETRIES + 1
    assert len(set(extrudes)) == 1
    assert action.reason == ("no grip window was judged at 4 mm^3/s (a longer"
                             " step_time in [measure_profile]?)")
    assert logged[0].startswith("no judged window in ")


def test_an_unsupported_fit_stops_the_run():
    # two levels whose points do not give a rising line
    procedure = make(temps=(200.0, 220.0), settings=proc.Settings(
        step_time_s=3.0, settle_time_s=2.0))
    action = procedure.start()
    time = 0.0
    level = 0
    while not isinstance(action, (proc.Stop, proc.Done)):
        answer = None
        if isinstance(action, proc.HeatTo):
            level += 1
        if isinstance(action, proc.Read):
            answer = proc.Reading(time, 200.0 + 20 * (level - 1), 0.3)
        elif isinstance(action, proc.Dwell):
            time += action.seconds
        elif isinstance(action, proc.Extrude):
            end = time + sum(action.moves_s)
            # the hotter level melts less: the fit refuses the line
            flow = 5.0 if level == 1 else 4.0
            for i in range(10):
                t = time + (i + 4) * (end - time) / 14
                procedure.window(window(t, t + 0.05, grip=0.5, flow=flow,
                                        temp=None))
            answer = proc.Extruded(time, end)
            time = end
        action = procedure.send(answer)
    assert isinstance(action, proc.Stop)
    assert "the flow does not rise with temperature" in action.reason


def test_the_first_step_that_slips_already_says_so():
    procedure = make(temps=(200.0, 220.0), start_flow=None)
    twin = Twin()
    # the twin melts half what the base profile expects
    twin.twin.melt = scaled_line(twin.twin.melt, 0.5)
    twin.run(procedure, until=lambda a: isinstance(a, proc.Release))
    steps = [a for a in twin.actions if isinstance(a, proc.Extrude)]
    assert len(steps) == 1
    assert said(twin)[-1] == (
        "level 1/2 (200 degC): the first step slipped already; the point is"
        " what the hotend melted (a lower START_FLOW= confirms it)")


def test_answers_must_fit_the_action():
    procedure = make()
    assert isinstance(procedure.start(), proc.Say)
    assert isinstance(procedure.send(), proc.HeatTo)
    assert isinstance(procedure.send(), proc.Read)
    with pytest.raises(TypeError):
        procedure.send(None)
    with pytest.raises(TypeError):
        procedure.send(proc.Extruded(0.0, 1.0))


# --- what it is built from ---------------------------------------------------
def test_the_bounds_are_the_base_s_or_the_given_ones_below_the_heater_s():
    b = proc.bounds_for(KNOWN, None, None, 300.0)
    assert (b.min_temp_c, b.recommended_temp_c, b.max_temp_c) == (185, 210, 250)
    b = proc.bounds_for(KNOWN, 190.0, 280.0, 240.0)
    assert (b.min_temp_c, b.recommended_temp_c, b.max_temp_c) == (190, 210, 240)
    b = proc.bounds_for(None, 180.0, 240.0, 300.0)
    assert b.recommended_temp_c == 210.0
    b = proc.bounds_for(KNOWN, 215.0, None, 300.0)
    assert b.recommended_temp_c == 215.0          # within the bounds
    with pytest.raises(FlowloopError, match="give MIN_TEMP= and MAX_TEMP="):
        proc.bounds_for(None, 180.0, None, 300.0)
    with pytest.raises(FlowloopError, match="MIN_TEMP: 260 degC is not below"
                       " the maximum 250 degC"):
        proc.bounds_for(KNOWN, 260.0, None, 300.0)


def test_settings_and_hardware():
    with pytest.raises(FlowloopError, match="20 is below settle_time 30"):
        proc.Settings(settle_time_s=30.0, max_settle_time_s=20.0)
    assert HARDWARE.filament_diameter_mm == 1.75
    assert dataclasses.replace(
        HARDWARE, filament_area_mm2=3.14159265 / 4 * 2.85 ** 2
    ).filament_diameter_mm == 2.85
    assert proc.move_times(2.5) == (1.0, 1.0, 0.5)
    assert proc.move_times(2.0) == (1.0, 1.0)


def test_without_a_base_the_identity_is_the_extruder_s():
    points = [MeasuredPoint(kind="into_air", temp_c=t, flow_mm3_s=f, grip=0.8,
                            heater_pwm=p)
              for t, f, p in ((200.0, 4.8, 80.0), (230.0, 8.4, 100.0))]
    procedure = make(temps=(200.0, 230.0), base=None, min_temp=180.0,
                     max_temp=260.0,
                     hardware=dataclasses.replace(HARDWARE,
                                                  nozzle_diameter_mm=0.6))
    # the levels, answered with the points above
    action = procedure.start()
    time, level = 0.0, -1
    while not isinstance(action, (proc.Done, proc.Stop)):
        answer = None
        if isinstance(action, proc.HeatTo):
            level += 1
        if isinstance(action, proc.Read):
            answer = proc.Reading(time, points[level].temp_c, 0.3)
        elif isinstance(action, proc.Dwell):
            time += action.seconds
        elif isinstance(action, proc.Extrude):
            end = time + sum(action.moves_s)
            grip = 0.8 if action.flow_mm3_s > points[level].flow_mm3_s else 1.0
            for i in range(10):
                t = time + (i + 4) * (end - time) / 14
                procedure.window(window(t, t + 0.05, grip=grip,
                                        flow=min(action.flow_mm3_s,
                                                 points[level].flow_mm3_s),
                                        temp=points[level].temp_c))
            answer = proc.Extruded(time, end)
            time = end
        action = procedure.send(answer)
    assert isinstance(action, proc.Done), action
    identity = action.profile.identity
    assert (identity.nozzle_diameter_mm, identity.filament_diameter_mm) == (
        0.6, 1.75)
    assert procedure.plan.min_grip == DEFAULT_MIN_GRIP


# --- the status --------------------------------------------------------------
def test_the_status_has_every_field_in_its_order():
    assert proc.Status().as_dict() == {
        'state': 'idle', 'name': None, 'level': None, 'flow': None,
        'levels': 0, 'message': '', 'points': [], 'result': None,
        'heater_control': None, 'heater_pwm': None}
    assert list(proc.Status().as_dict()) == [
        'state', 'name', 'level', 'flow', 'levels', 'message', 'points',
        'result', 'heater_control', 'heater_pwm']
    point = MeasuredPoint(kind="into_air", temp_c=200.0, flow_mm3_s=5.0,
                          grip=0.85, heater_pwm=80.0)
    status = proc.Status(state=proc.State.RUNNING, name='x').with_progress(
        proc.Progress(levels=2, level=1, flow=5.5, points=(point,)))
    assert status.as_dict()['points'] == [
        {'temp_c': 200.0, 'flow_mm3_s': 5.0, 'grip': 0.85, 'heater_pwm': 80.0}]
    assert (status.level, status.flow, status.levels) == (1, 5.5, 2)
    result = proc.Result.of(KNOWN, 'real_print')
    assert dataclasses.replace(status, result=result).as_dict()['result'] == {
        'name': 'known', 'slope_mm3_s_per_c': SLOPE, 'temp_c': TEMP,
        'flow_mm3_s': FLOW, 'note': KNOWN.provenance.note}


# --- the real-print measurement ----------------------------------------------
def test_a_print_measurement_needs_an_active_profile():
    with pytest.raises(FlowloopError, match="activate the material's profile"):
        proc.print_base(None)
    assert proc.print_base(KNOWN) is KNOWN
    m = proc.PrintMeasurement("printed", KNOWN, None, HARDWARE)
    assert m.watch.min_grip == DEFAULT_MIN_GRIP


def test_a_print_measurement_ends_on_a_fault():
    m = proc.PrintMeasurement("printed", KNOWN, 0.9, HARDWARE)
    assert m.window(window(0.0, 1.0, grip=None, reason=FAULT)) == proc.Stop(
        "flow sensor fault: nothing stored")


def test_a_print_measurement_finds_the_real_print_point_by_layer():
    m = proc.PrintMeasurement("printed", KNOWN, 0.9, HARDWARE)
    m.add_layer(0.0, 5.0)
    m.add_layer(10.0, 7.0)
    step = None
    for i in range(20):
        t = 10.0 + i
        step = m.window(window(t, t + 1.0, grip=0.85, flow=5.5, temp=210.0))
        if step is not None:
            break
    assert isinstance(step, measure.StepResult)
    done = m.finish(step)
    assert isinstance(done, proc.Done) and done.notes == ()
    point, = done.points
    assert point.flow_mm3_s == pytest.approx(0.85 * 7.0)
    assert point.kind == "real_print" and point.heater_pwm is None
    real = done.profile.lines.real_print
    assert real.slope_mm3_s_per_c == SLOPE
    assert done.profile.provenance.source == "MEASURE_MATERIAL_PROFILE_PRINT"
    assert done.lines[0].startswith("grip 0.850 at 5.95 mm^3/s, 210.0 degC:"
                                    " real_print line: ")
    # without MEASURE_MATERIAL_PROFILE_LAYER: the windows' own flow, noted
    m = proc.PrintMeasurement("printed", KNOWN, 0.9, HARDWARE)
    done = m.finish(step)
    assert done.points[0].flow_mm3_s == pytest.approx(5.5)
    assert done.notes[0].startswith("no MEASURE_MATERIAL_PROFILE_LAYER")


# --- what the adapter asks between its turns ---------------------------------
def test_a_run_ends_before_a_turn_on_what_a_command_in_between_changed():
    control = object()
    left = ((0.0, 0.0, 5.0, 12.0), 185.0, control)

    def stop(now=left, cancel=None, paused=False, last=left):
        return proc.turn_stop("extruder", cancel, paused, last, now)
    assert stop() is None
    assert stop(last=None, now=None) is None
    assert stop(cancel="cancelled (x)", paused=True) == "cancelled (x)"
    assert stop(paused=True) == "PAUSE cancels a measurement"
    assert stop(((0.0, 0.0, 10.0, 12.0), 185.0, control)) == (
        "the toolhead was moved by another command: cancelled")
    assert stop(((0.0, 0.0, 5.0, 12.0), 230.0, control)) == (
        "extruder's target was changed by another command (185 -> 230"
        " degC): cancelled")
    assert stop(((0.0, 0.0, 5.0, 12.0), 185.0, object())) == (
        "extruder's heater control was replaced by another command:"
        " cancelled")


def test_a_run_without_its_sensor_names_what_is_missing():
    # which sensor a run takes: klipper_config.find_flow_sensor (its tests)
    assert proc.missing_sensor("c", "extruder") == (
        "EXTRUDER: [flow_sensor c] is needed to judge grip")
    assert proc.missing_sensor(None, "extruder2") == (
        "EXTRUDER: a [flow_sensor] on extruder2 is needed to judge grip")


def test_the_ramp_reads_the_temperature_once_between_two_steps():
    procedure = make(temps=(200.0, 220.0))
    twin = Twin()
    assert isinstance(twin.run(procedure), proc.Done)
    first = next(i for i, a in enumerate(twin.actions)
                 if isinstance(a, proc.Release))
    twin.actions = twin.actions[:first]    # the first level's ramp
    steps = [i for i, a in enumerate(twin.actions) if isinstance(a, proc.Extrude)]
    assert len(steps) >= 3
    for a, b in zip(steps, steps[1:]):
        reads = [x for x in twin.actions[a:b] if isinstance(x, proc.Read)]
        assert len(reads) == 1, twin.actions[a:b]
    # and one before the first step, after the level settled
    assert isinstance(twin.actions[steps[0] - 1], proc.Read)


# --- what the adapter asks before a start, and says after --------------------
def test_a_start_is_refused_while_busy_printing_or_paused():
    assert proc.start_refusal(False) is None
    assert proc.start_refusal(False, printing=False, paused=False) is None
    assert proc.start_refusal(True, printing=True, paused=True) == (
        "a measurement is running already")
    assert proc.start_refusal(False, printing=True, paused=True) == (
        "a print is running; nothing changed")
    assert proc.start_refusal(False, paused=True) == (
        "the printer is paused (RESUME or CLEAR_PAUSE first); nothing changed")


def test_only_the_active_extruder_is_measured():
    proc.check_active("extruder1", True)
    with pytest.raises(FlowloopError, match="^extruder1 is not the active"
                       r" extruder \(activate it first\)$"):
        proc.check_active("extruder1", False)


def test_the_hand_over_is_said_with_the_extruder_only_when_activated():
    assert proc.handed_over("X", "pla", "extruder", False) == (
        "X: profile 'pla' handed to Moonraker")
    assert proc.handed_over("X", "pla", "extruder1", True) == (
        "X: profile 'pla' handed to Moonraker and activated on extruder1")
    assert proc.not_stored("X", "pla", "no method") == (
        "X: profile 'pla' measured but not stored (no method): is"
        " Moonraker's [flowloop] component loaded?")


def test_a_shutdown_stops_the_run_at_its_next_reading_without_reading():
    procedure = make()
    action = Twin().run(procedure, until=lambda a: isinstance(a, proc.Dwell))
    procedure.shutdown()
    assert procedure.stop_reason == "Klipper shut down"
    assert procedure.send() == proc.Stop("Klipper shut down")
    # a cancel before it is the reason said
    procedure = make()
    Twin().run(procedure, until=lambda a: isinstance(a, proc.Dwell))
    procedure.cancel("cancelled (CANCEL_MATERIAL_PROFILE)")
    procedure.shutdown()
    assert procedure.send() == proc.Stop("cancelled (CANCEL_MATERIAL_PROFILE)")
    assert isinstance(action, proc.Dwell)


def test_the_status_moves_through_its_states():
    S = proc.State
    done = proc.Done(KNOWN, None, (), ())
    started = proc.Status(message="old", result=proc.Result.of(KNOWN)) \
        .with_heater("ControlPID").running("pla")
    assert (started.state, started.name, started.result, started.message,
            started.heater_control) == (S.RUNNING, "pla", None, "", "ControlPID")
    held = started.with_heater("FixedPowerControl", 0.4)
    assert (held.heater_control, held.heater_pwm) == ("FixedPowerControl", 0.4)
    assert held.as_dict()["state"] == "running"
    measured = held.measured(done, "into_air")
    assert measured.state is S.MEASURED and measured.result.name == "known"
    assert measured.not_stored("why").state is S.MEASURED
    assert measured.not_stored("why").message == "why"
    assert measured.stored("kept").as_dict()["state"] == "stored"
    aborted = held.aborted("stopped")
    assert (aborted.state, aborted.message) == (S.ABORTED, "stopped")
    # a print watched: nothing of a run before it is left
    point = MeasuredPoint(kind="into_air", temp_c=200.0, flow_mm3_s=5.0,
                          grip=0.85, heater_pwm=0.4)
    ran = measured.with_progress(proc.Progress(levels=3, level=2, flow=5.5,
                                               points=(point,)))
    watching = ran.watching("printed", "watching")
    assert (watching.state, watching.name, watching.level, watching.levels,
            watching.flow, watching.points, watching.result,
            watching.message) == (S.WATCHING, "printed", None, 0, None, (),
                                  None, "watching")
    assert [s.value for s in S] == ["idle", "running", "watching", "measured",
                                    "stored", "aborted"]


def test_a_status_is_built_into_a_dict_once():
    # klippy's status poll hands out the same dict until the status changes
    status = proc.Status().running("pla")
    assert status.as_dict() is status.as_dict()
    changed = status.aborted("cancelled")
    assert changed.as_dict() is not status.as_dict()
    assert changed.as_dict()["state"] != status.as_dict()["state"]
    assert changed == dataclasses.replace(changed)   # the cache is no field
