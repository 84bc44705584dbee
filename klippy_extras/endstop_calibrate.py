# Delta tower endstop calibration (ENDSTOP_CALIBRATE)
#
# Probes near each tower (and the centre, and by default opposite each tower)
# through Klipper's probe helpers, then solves the three position_endstop
# values exactly (flowloop.calibrate.delta) and stages them for SAVE_CONFIG. Delta
# geometry is only read at startup: a second call after the restart checks
# the result (within tolerance, nothing is staged).
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import collections
import functools
import logging

# The shared module first: it turns a requirement of the core missing from
# klippy's Python into a config error
from . import flowloop as flowloop_host

# isort: split
from flowloop.calibrate import delta
from flowloop.errors import FlowloopError
from flowloop.host import klipper_config

try:    # klippy/extras/ (Klipper)
    from . import probe
except ImportError:  # klippy/plugins/ (Kalico): klippy's extras one up
    from ..extras import probe

TOWERS = delta.TOWERS
# What Klipper's ProbePointsHelper hands its callback (manual_probe.ProbeResult)
ProbeResult = collections.namedtuple('ProbeResult', [
    'bed_x', 'bed_y', 'bed_z', 'test_x', 'test_y', 'test_z'])


def _probe_result(test_pos, offsets):
    """Klipper's manual_probe.create_probe_result, for a host without it."""
    x_offset, y_offset, z_offset = offsets[:3]
    return ProbeResult(test_pos[0] + x_offset, test_pos[1] + y_offset,
                       test_pos[2] - z_offset, *test_pos[:3])
METHODS = ('automatic', 'manual')
# Parameters of ENDSTOP_CALIBRATE that the probe itself must not see.
OWN_PARAMS = ('SAMPLES', 'RADIUS', 'TOLERANCE')
# Numbers the probe reads with Klipper's get_float, which lets nan through:
# read here first (the probe checks its own ranges after)
PROBE_NUMBERS = ('PROBE_SPEED', 'LIFT_SPEED', 'SAMPLE_RETRACT_DIST',
                 'SAMPLES_TOLERANCE', 'HORIZONTAL_MOVE_Z', 'SPEED')
PROBE_INTEGERS = ('SAMPLES_TOLERANCE_RETRIES',)


class EndstopCalibrate:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.host = self.printer.load_object(config, 'flowloop')
        self.name = config.get_name()
        kinematics = config.getsection('printer').get('kinematics', '')
        if kinematics.strip() != 'delta':
            raise config.error(klipper_config.option_message(
                'printer', 'kinematics', f"[{self.name}] is for linear delta"
                f" printers (kinematics: delta), not {kinematics}"))
        # floats through one reader: Klipper's bounds, then nan/inf refused
        getfloat = functools.partial(klipper_config.finite_float, config)
        self.radius = getfloat('radius', above=0.)
        self.samples = config.getint('samples', 1, minval=1,
                                     maxval=delta.MAX_SAMPLES)
        self.tolerance = getfloat('tolerance', delta.DEFAULT_TOLERANCE_MM,
                                  above=0.)
        self.geometry_warning = getfloat(
            'geometry_warning', delta.DEFAULT_GEOMETRY_WARNING_MM, above=0.)
        self.opposite_points = config.getboolean('opposite_points', True)
        has_points = config.get('points', None) is not None
        self.probe_helper = probe.ProbePointsHelper(
            config, self.probe_finalize,
            default_points=delta.probe_points(
                delta.DEFAULT_ANGLES_DEG, self.radius, self.opposite_points))
        self.probe_helper.minimum_points(3)
        # Points from the config, or None to place them from RADIUS.
        self.fixed_points = None
        if has_points:
            self.fixed_points = list(self.probe_helper.probe_points)
        self.active = None
        self.last_result = {}
        self.gcode = self.printer.lookup_object('gcode')
        self.gcode.register_command('ENDSTOP_CALIBRATE',
                                    self.cmd_ENDSTOP_CALIBRATE,
                                    desc=self.cmd_ENDSTOP_CALIBRATE_help)
        self.printer.register_event_handler('klippy:connect',
                                            self._handle_connect)

    def _handle_connect(self):
        self.toolhead = self.printer.lookup_object('toolhead')
        if self.fixed_points is None:
            problem = self._radius_problem(self.radius)
            if problem:
                raise self.printer.config_error(klipper_config.option_message(
                    self.name, 'radius', problem))

    def _max_radius(self):
        kin = self.toolhead.get_kinematics()
        status = kin.get_status(self.printer.get_reactor().monotonic())
        return status['axis_maximum'][0]

    def _radius_problem(self, radius):
        max_radius = self._max_radius()
        if radius > max_radius:
            return (f"{radius:.3f} is outside the printable radius"
                    f" {max_radius:.3f}")
        return None

    def _geometry(self):
        cal = self.toolhead.get_kinematics().get_calibration()
        return delta.DeltaGeometry(cal.radius, tuple(cal.arms),
                                   tuple(cal.endstops), tuple(cal.angles))

    cmd_ENDSTOP_CALIBRATE_help = (
        "Probe near each delta tower and solve the tower endstops")

    def cmd_ENDSTOP_CALIBRATE(self, gcmd):
        method = gcmd.get('METHOD', 'automatic').lower()
        if method not in METHODS:
            raise gcmd.error("ENDSTOP_CALIBRATE: METHOD must be automatic"
                             f" or manual, not '{method}'")
        samples = flowloop_host.gcode_integer(gcmd, 'SAMPLES', self.samples,
                                              minimum=1,
                                              maximum=delta.MAX_SAMPLES)
        tolerance = flowloop_host.gcode_number(gcmd, 'TOLERANCE',
                                               self.tolerance, above=0.)
        radius = flowloop_host.gcode_number(gcmd, 'RADIUS', None, above=0.)
        for name in PROBE_NUMBERS:
            flowloop_host.gcode_number(gcmd, name, None)
        for name in PROBE_INTEGERS:
            flowloop_host.gcode_integer(gcmd, name, None, minimum=0)
        if radius is not None and self.fixed_points is not None:
            raise gcmd.error("ENDSTOP_CALIBRATE: RADIUS cannot move the"
                             f" points configured in [{self.name}]")
        if self.fixed_points is not None:
            points = self.fixed_points
        else:
            if radius is None:
                radius = self.radius
            problem = self._radius_problem(radius)
            if problem:
                raise gcmd.error(f"ENDSTOP_CALIBRATE: RADIUS={problem}")
            points = delta.probe_points(self._geometry().angles_deg, radius,
                                        self.opposite_points)
        self.active = {'samples': samples, 'tolerance': tolerance}
        # Each point repeated SAMPLES times in a row; the median is ours.
        self.probe_helper.update_probe_points(
            [p for p in points for _ in range(samples)], 3)
        params = {k: v for k, v in gcmd.get_command_parameters().items()
                  if k.upper() not in OWN_PARAMS}
        probe_gcmd = self.gcode.create_gcode_command(
            gcmd.get_command(), gcmd.get_commandline(), params)
        self.probe_helper.start_probe(probe_gcmd)

    def probe_finalize(self, results, positions=None):
        if positions is not None:
            # Kalico's ProbePointsHelper (Klipper's form before ProbeResult):
            # the probe's offsets, then where the toolhead was at each trigger
            results = [_probe_result(pos, results) for pos in positions]
        active = self.active
        rows = [(p.test_x, p.test_y, p.test_z, p.test_z - p.bed_z)
                for p in results]
        before = self._geometry()
        try:
            medians = delta.median_of_samples(rows, active['samples'])
            solution = delta.solve_endstops(
                before, medians[:, :3], medians[:, 3],
                geometry_warning_mm=self.geometry_warning)
        except FlowloopError as e:
            raise self.gcode.error(f"ENDSTOP_CALIBRATE: {e}") from None
        tolerance = active['tolerance']
        check = delta.check_flatness(solution.heights_before_mm, tolerance)
        staged, paste = [], []
        if not check.within_tolerance:
            staged, paste = self.host.stage_for_save_config(
                [(name, 'position_endstop', f"{value:.6f}")
                 for name, value in zip(TOWERS, solution.position_endstop)])
        self._report(solution, check, staged, paste)
        self.last_result = {
            'points': len(medians),
            'samples': active['samples'],
            'tolerance': tolerance,
            'within_tolerance': check.within_tolerance,
            'staged': bool(staged),
            'position_endstop_before': tuple(solution.position_endstop_before),
            'position_endstop': tuple(solution.position_endstop),
            'spread_before_mm': solution.spread_before_mm,
            'mean_height_before_mm': check.mean_height_mm,
            'spread_after_mm': solution.spread_after_mm,
            'residual_mm': solution.residual_mm,
            'geometry_warning': solution.geometry_warning or '',
        }
        logging.info("ENDSTOP_CALIBRATE heights before %s after %s",
                     solution.heights_before_mm, solution.heights_after_mm)

    def _report(self, solution, check, staged, paste):
        lines = [f"ENDSTOP_CALIBRATE: {len(solution.heights_before_mm)} points,"
                 f" spread {solution.spread_before_mm:.4f} mm,"
                 f" mean height {check.mean_height_mm:.4f} mm"]
        for i, name in enumerate(TOWERS):
            k = solution.tower_probe_index[i]
            lines.append(
                f"{name}: position_endstop"
                f" {solution.position_endstop_before[i]:.4f} ->"
                f" {solution.position_endstop[i]:.4f} (height near tower"
                f" {solution.heights_before_mm[k]:.4f} ->"
                f" {solution.heights_after_mm[k]:.4f} mm)")
        lines.append(f"predicted spread after: {solution.spread_after_mm:.4f}"
                     f" mm (residual {solution.residual_mm:.4f} mm)")
        if solution.geometry_warning:
            lines.append("WARNING: " + solution.geometry_warning)
        if check.within_tolerance:
            lines.append(f"Within {check.tolerance_mm:.4f} mm: nothing to"
                         " change.")
        else:
            lines += klipper_config.save_report(staged, paste)
            lines.append("Delta geometry is read at startup: after the"
                         " restart, G28 and ENDSTOP_CALIBRATE again to check.")
        self.gcode.respond_info("\n".join(lines))

    def get_status(self, eventtime):
        return {'last_result': self.last_result}


def load_config(config):
    return EndstopCalibrate(config)
