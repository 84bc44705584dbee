# Differential A/B rotation_distance calibration (DIFF_AB_CALIBRATE) and
# WAIT_BED_EQUILIBRIUM.
#
# From caliper readings of the pylon print (flowloop ab-pylons), the core
# (flowloop.calibrate.diff_ab) computes the scale of motor A (stepper_x) and motor B
# (stepper_y) on CoreXY, or of X and Y on a cartesian printer. Both axes are
# validated before either stepper changes; the new rotation_distance is
# applied at runtime and staged for SAVE_CONFIG.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import functools
import re

# The shared module first: it turns a requirement of the core missing from
# klippy's Python into a config error
from . import flowloop as flowloop_host

# isort: split
from flowloop.calibrate import diff_ab
from flowloop.errors import FlowloopError
from flowloop.host import klipper_config

# stepper_x, stepper_x1, ... all move with motor A (X on cartesian)
AXIS_STEPPER_RE = {axis: re.compile(re.escape(name) + r'\d*$')
                   for axis, name in diff_ab.AXIS_STEPPERS.items()}
HISTORY_LENGTH = 10
SAMPLE_PERIOD_S = 1.


class DiffABCalibrate:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.host = self.printer.load_object(config, 'flowloop')
        self.name = config.get_name()
        self.kinematics = config.getsection('printer').get(
            'kinematics', '').strip()
        # floats through one reader: Klipper's bounds, then nan/inf refused
        getfloat = functools.partial(klipper_config.finite_float, config)
        d1, d2 = diff_ab.NOMINAL_DISTANCES_MM
        self.d1 = getfloat('d1', d1, above=0.)
        self.d2 = getfloat('d2', d2, above=self.d1)
        max_scale_change_pct = getfloat(
            'max_scale_change', 100. * diff_ab.MAX_SCALE_CHANGE,
            above=0., maxval=100. * diff_ab.MAX_SCALE_CHANGE_CEILING)
        self.max_scale_change = max_scale_change_pct / 100.
        default = diff_ab.ErrorBudget()
        caliper_accuracy = getfloat(
            'caliper_accuracy', default.caliper_accuracy_mm, minval=0.)
        caliper_range = getfloat(
            'caliper_range', default.caliper_range_mm, above=0.)
        reading_error = getfloat(
            'reading_error', default.reading_error_mm, minval=0.)
        self.bed_heater_name = config.get('bed_heater', 'heater_bed')
        self.tolerance = getfloat(
            'equilibrium_tolerance', diff_ab.EQUILIBRIUM_TOLERANCE_PCT_PER_MIN,
            above=0.)
        self.window = getfloat(
            'equilibrium_window', diff_ab.EQUILIBRIUM_WINDOW_S, above=1.)
        self.timeout = getfloat(
            'equilibrium_timeout', diff_ab.EQUILIBRIUM_TIMEOUT_S, above=0.)
        self.band = getfloat(
            'equilibrium_band', diff_ab.EQUILIBRIUM_BAND_C, above=0.)
        self.report_interval = getfloat('report_interval', 10., above=0.)
        try:
            self.budget = diff_ab.ErrorBudget(
                caliper_accuracy_mm=caliper_accuracy,
                caliper_range_mm=caliper_range, reading_error_mm=reading_error)
        except FlowloopError as e:
            raise config.error(str(e)) from None
        self.steppers = {'a': [], 'b': []}
        self.history = []
        self.last_result = None
        self.bed_state = None
        self._update_status()
        self.toolhead = None
        self.gcode = self.printer.lookup_object('gcode')
        self.gcode.register_command('DIFF_AB_CALIBRATE',
                                    self.cmd_DIFF_AB_CALIBRATE,
                                    desc=self.cmd_DIFF_AB_CALIBRATE_help)
        self.gcode.register_command('WAIT_BED_EQUILIBRIUM',
                                    self.cmd_WAIT_BED_EQUILIBRIUM,
                                    desc=self.cmd_WAIT_BED_EQUILIBRIUM_help)
        self.printer.register_event_handler('klippy:connect',
                                            self._handle_connect)

    def _handle_connect(self):
        self.toolhead = self.printer.lookup_object('toolhead')
        for stepper in self.toolhead.get_kinematics().get_steppers():
            for axis, pattern in AXIS_STEPPER_RE.items():
                if pattern.match(stepper.get_name()):
                    self.steppers[axis].append(stepper)
        self._update_status()

    # --- DIFF_AB_CALIBRATE ------------------------------------------------

    def _reading_sets(self, gcmd):
        """Both axes' reading sets from A<k>=, B<k>=, D<k>= (k = 1..9)."""
        ks = range(1, diff_ab.MAX_DISTANCES + 1)
        nominals = {1: self.d1, 2: self.d2}
        nominals.update({k: number(gcmd, f"D{k}", **diff_ab.NOMINAL_DISTANCE_PARAM)
                         for k in ks if gcmd.get(f"D{k}", None) is not None})
        readings = {axis: {k: gcmd.get(f"{axis.upper()}{k}") for k in ks
                           if gcmd.get(f"{axis.upper()}{k}", None) is not None}
                    for axis in 'ab'}
        sets = {axis: diff_ab.numbered_reading_sets(axis, readings[axis], nominals)
                for axis in 'ab'}
        diff_ab.check_nominals_used(
            [k for k in ks if gcmd.get(f"D{k}", None) is not None],
            set(readings['a']) | set(readings['b']))
        return sets['a'], sets['b']

    def _rotation_distance(self, axis):
        steppers = self.steppers[axis]
        if not steppers:
            raise self.printer.command_error(
                f"no {diff_ab.AXIS_STEPPERS[axis]} stepper found")
        return steppers[0].get_rotation_distance()[0]

    def _plan(self, gcmd):
        """Everything decided and checked; nothing changed yet."""
        force = integer(gcmd, 'FORCE', 0, minimum=0, maximum=1)
        try:
            # the kinematics first: no point asking for readings on a delta
            kin = diff_ab.check_kinematics(self.kinematics)
            sets_a, sets_b = self._reading_sets(gcmd)
            calibration = diff_ab.calibrate(
                kin, self._rotation_distance('a'), self._rotation_distance('b'),
                sets_a, sets_b,
                budget=self.budget, max_scale_change=self.max_scale_change,
                force=bool(force), force_hint="FORCE=1")
        except FlowloopError as e:
            raise gcmd.error(f"DIFF_AB_CALIBRATE: {e}") from None
        changes = []
        for result in calibration.axes():
            for stepper in self.steppers[result.axis]:
                old = stepper.get_rotation_distance()[0]
                changes.append((stepper, old, old * result.fit.scale))
        return calibration, changes

    def _apply(self, changes):
        """Apply now, stage for SAVE_CONFIG: (staged, lines to paste)."""
        self.toolhead.flush_step_generation()
        for stepper, _old, new in changes:
            stepper.set_rotation_distance(new)
        # The axes' positions no longer match the new scale: home again.
        self.toolhead.get_kinematics().clear_homing_state('xy')
        return self.host.stage_for_save_config(
            [(stepper.get_name(), 'rotation_distance', f"{new:.6f}")
             for stepper, _old, new in changes])

    cmd_DIFF_AB_CALIBRATE_help = (
        "Set A/B (X/Y) rotation_distance from pylon caliper readings:"
        " A1=.. A2=.. B1=.. B2=.. [D1=10 D2=150] [FORCE=1]")

    def cmd_DIFF_AB_CALIBRATE(self, gcmd):
        calibration, changes = self._plan(gcmd)
        staged, paste = self._apply(changes)
        self.history = diff_ab.append_history(self.history, calibration,
                                              keep=HISTORY_LENGTH)
        self.last_result = calibration.as_dict()
        self._update_status()
        lines = calibration.report_lines()
        for stepper, old, new in changes:
            lines.append(f"{stepper.get_name()}: rotation_distance"
                         f" {old:.6f} -> {new:.6f} (applied now)")
        lines += klipper_config.save_report(staged, paste)
        lines.append("X and Y are no longer homed: run G28 before moving.")
        gcmd.respond_info("\n".join(lines))

    # --- WAIT_BED_EQUILIBRIUM -----------------------------------------------

    cmd_WAIT_BED_EQUILIBRIUM_help = (
        "Wait until the bed heater's power stops falling"
        " [TOLERANCE=%/min] [TIMEOUT=s]")

    def cmd_WAIT_BED_EQUILIBRIUM(self, gcmd):
        tolerance = number(gcmd, 'TOLERANCE', self.tolerance, above=0.)
        timeout = number(gcmd, 'TIMEOUT', self.timeout, above=0.)
        heater = self.printer.lookup_object(self.bed_heater_name, None)
        if heater is None or not hasattr(heater, 'get_status'):
            self._set_bed_state('no_heater')
            gcmd.respond_info(f"No heater '{self.bed_heater_name}':"
                              " an unheated bed needs no wait.")
            return
        try:
            detector = diff_ab.BedEquilibrium(tolerance, self.window, self.band)
        except FlowloopError as e:
            raise gcmd.error(str(e)) from None
        reactor = self.printer.get_reactor()
        start = eventtime = reactor.monotonic()
        next_report = start
        while not self.printer.is_shutdown():
            status = heater.get_status(eventtime)
            state = detector.add(eventtime - start, status['power'],
                                 status['temperature'], status['target'])
            self._set_bed_state(state)
            if state == 'off':
                gcmd.respond_info("Bed heater is off: nothing to wait for.")
                return
            if state == 'equilibrium':
                gcmd.respond_info("Bed at equilibrium: "
                                  + self._progress(status, detector))
                return
            if eventtime - start >= timeout:
                self._set_bed_state('timeout')
                gcmd.respond_info(
                    f"!! Bed not at equilibrium after {timeout:.0f} s"
                    f" ({self._progress(status, detector)}); continuing.")
                return
            if eventtime >= next_report:
                gcmd.respond_info(f"Waiting for bed equilibrium ({state}): "
                                  + self._progress(status, detector))
                next_report = eventtime + self.report_interval
            self.toolhead.get_last_move_time()
            eventtime = reactor.pause(eventtime + SAMPLE_PERIOD_S)

    def _progress(self, status, detector):
        slope = detector.slope_pct_per_min()
        trend = ("power trend n/a" if slope is None
                 else f"power {slope:+.2f} %/min"
                      f" (limit -{detector.tolerance_pct_per_min:.2f})")
        return (f"{status['temperature']:.1f}/{status['target']:.1f} C,"
                f" power {100. * status['power']:.1f} %, {trend},"
                f" {detector.covered_s():.0f}/{detector.window_s:.0f} s"
                " at temperature")

    def _set_bed_state(self, state):
        self.bed_state = state
        self.status = dict(self.status, bed_state=state)

    def _update_status(self):
        """Rebuilt when something it shows changes, never in get_status."""
        rd = {}
        for axis in ('a', 'b'):
            for stepper in self.steppers[axis]:
                rd[stepper.get_name()] = stepper.get_rotation_distance()[0]
        self.status = {
            'kinematics': self.kinematics,
            'rotation_distance': rd,
            'last_result': self.last_result,
            'iterations': self.history[-1]['iteration'] if self.history else 0,
            'history': tuple(self.history),
            'bed_state': self.bed_state}

    def get_status(self, eventtime=None):
        return self.status

number = flowloop_host.gcode_number
integer = flowloop_host.gcode_integer


def load_config(config):
    return DiffABCalibrate(config)
