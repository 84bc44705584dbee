# [flow_sensor NAME]: an EMS22 encoder riding on the filament after the
# feeder, grip from sensor vs commanded filament, and the two calibrations
# it enables.
#
# The pipeline (decoding, grip windows, faults, the status policy) lives in
# flowloop (pure Python: flowloop.sensor.pipeline); this module reads config,
# talks to the MCU and the toolhead, and reports. The samples come from a
# source object (SOURCES at the end) as sensor_bulk_data payloads, handed to
# the pipeline on the reactor, in batches. The simulated sensor of demos and
# tests is a section of its own, [flow_sensor_simulation NAME], which builds
# this same FlowSensor on its twin source: a printer without that section
# never imports it.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import logging

# The shared module first: it turns a requirement of the core missing from
# klippy's Python into a config error
from .. import flowloop as flowloop_host

# isort: split
from flowloop.calibrate import flow_sensor as sensor_cal
from flowloop.errors import FlowloopError
from flowloop.host import klipper_config
from flowloop.sensor import ems22
from flowloop.sensor import grip as flow_grip
from flowloop.sensor import pipeline as fl_pipeline

# A package (this file and source.py): klippy/extras/flow_sensor/ on
# Klipper, klippy/plugins/flow_sensor/ on Kalico
if (__package__ or '').startswith('klippy.'):
    # Kalico: klippy.plugins.flow_sensor, klippy's modules two up
    from ... import chelper
    from ...extras import bulk_sensor
else:   # Klipper: klippy/extras/flow_sensor/, extras one up
    import chelper

    from .. import bulk_sensor
from .source import Ems22Source

BATCH_INTERVAL = 0.100
DUMP_INTERVAL = 0.100
SAMPLE_WAIT_TIMEOUT = 2.0
# Which way the counts run depends on the side of the filament the axle sits
DIRECTIONS = {'forward': 1., 'reverse': -1.}


class FlowSensor:
    """The sensor's pipeline and commands, fed by source_class(config, self):
    an Ems22Source here, the twin for [flow_sensor_simulation NAME]."""

    def __init__(self, config, source_class):
        self.printer = printer = config.get_printer()
        printer.load_object(config, 'flowloop')
        self.reactor = printer.get_reactor()
        self.section = config.get_name()
        self.name = self.section.split()[-1]
        self.spi_mode = config.getint('spi_mode', ems22.DEFAULT_SPI_MODE,
                                      minval=0, maxval=3)
        low, high = ems22.SAMPLE_PERIOD_RANGE_S
        self.sample_period = config.getfloat(
            'sample_period', ems22.DEFAULT_SAMPLE_PERIOD_S, minval=low,
            maxval=high)
        self.extruder_name = config.get('extruder', 'extruder')
        self.counts_per_mm = config.getfloat(
            'counts_per_mm', ems22.DEFAULT_COUNTS_PER_MM, above=0.)
        self.direction_sign = config.getchoice('direction', DIRECTIONS,
                                               'forward')
        low, high = sensor_cal.CALIBRATION_RANGE
        calibration = config.getfloat('calibration', 1., minval=low,
                                      maxval=high)
        low, high = flow_grip.WINDOW_MM_RANGE
        grip_window = config.getfloat('grip_window', flow_grip.DEFAULT_WINDOW_MM,
                                      minval=low, maxval=high)
        fault_samples = config.getint('fault_samples',
                                      ems22.DEFAULT_FAULT_SAMPLES, minval=1)
        self.on_fault = config.getchoice('on_fault', {'warn': 'warn',
                                                      'pause': 'pause'}, 'warn')
        # As filament_switch_sensor's runout helper: pause_resume at config time
        self.pause_resume = None
        if self.on_fault == 'pause':
            self.pause_resume = printer.load_object(config, 'pause_resume')
        self.pipeline = fl_pipeline.SensorPipeline(fl_pipeline.Settings(
            counts_per_mm=self.counts_per_mm, direction_sign=self.direction_sign,
            spi_mode=self.spi_mode, sample_period_s=self.sample_period,
            window_mm=grip_window, calibration=calibration,
            fault_samples=fault_samples))
        self.motion = ExtruderMotion(self)
        self.window_callbacks = []
        self.dump_samples = None
        self.status = self.status_parts = None   # get_status's, when built
        self.extruder = self.toolhead = self.heater = None
        self.source = source_class(config, self)
        self.batch_bulk = bulk_sensor.BatchBulkHelper(
            printer, self._dump_batch, self._dump_start, self._dump_stop,
            DUMP_INTERVAL)
        self.batch_bulk.add_mux_endpoint(
            "flow_sensor/dump_flow", "sensor", self.name,
            {'header': ('time', 'filament_mm', 'commanded_mm')})
        printer.register_event_handler('klippy:connect', self._handle_connect)
        printer.register_event_handler('klippy:ready', self._handle_ready)
        self._register_commands(config)

    def _register_commands(self, config):
        for cmd, func, desc in [
                ('QUERY_FLOW_SENSOR', self.cmd_QUERY_FLOW_SENSOR,
                 self.cmd_QUERY_FLOW_SENSOR_help),
                ('CALIBRATE_FLOW_SENSOR', self.cmd_CALIBRATE_FLOW_SENSOR,
                 self.cmd_CALIBRATE_FLOW_SENSOR_help),
                ('CALIBRATE_EXTRUDER_ROTATION_DISTANCE',
                 self.cmd_CALIBRATE_EXTRUDER_ROTATION_DISTANCE,
                 self.cmd_CALIBRATE_EXTRUDER_ROTATION_DISTANCE_help)]:
            self.register_command(cmd, func, desc, config)

    def register_command(self, cmd, func, desc, config):
        """A command of this sensor, SENSOR=name (its source's too)."""
        gcode = self.printer.lookup_object('gcode')
        gcode.register_mux_command(cmd, 'SENSOR', self.name, func, desc=desc)
        try:
            # The first sensor also answers commands without SENSOR=
            gcode.register_mux_command(cmd, 'SENSOR', None, func, desc=desc)
        except config.error:
            pass

    # --- setup ---------------------------------------------------------------
    def _handle_connect(self):
        self.extruder = klipper_config.extruder_for(self.printer, self.section,
                                                    self.extruder_name)
        self.toolhead = self.printer.lookup_object('toolhead')
        self.heater = self.extruder.get_heater()
        area = getattr(self.extruder, 'filament_area', None)
        if area:
            self.pipeline.set_filament_area(area)
        self.source.connect(self)

    def _handle_ready(self):
        self.source.start()
        self.reactor.register_timer(self._batch_timer, self.reactor.NOW)

    def _batch_timer(self, eventtime):
        self.source.catch_up()
        return eventtime + BATCH_INTERVAL

    # --- the public interface for other flowloop sections ---------------------
    def subscribe_grip_windows(self, callback):
        """callback(window) runs in the reactor for every closed grip window
        (a frozen flowloop.window.Window); while the sensor is faulted
        windows come unjudged (grip None, reason 'fault'). It must not pause
        the reactor (it may run inside motion_queuing's flush)."""
        self.window_callbacks.append(callback)
        self.pipeline.want_flows = True

    def sync(self, until=None):
        """Process the samples up to print time `until` now (after the
        caller's wait_moves; in batch mode the steps are generated first)."""
        self.source.sync(until)

    def simulated_hotend(self):
        """The hotend (HotendParams) a simulated sensor's twin heats, which
        batch mode's thermal estimate follows; None for a real sensor or a
        twin without heater_power."""
        return self.source.hotend_params()

    def hotend_reading(self, eventtime):
        """(temperature degC, heater power 0..1) of the hotend the sensor's
        windows are stamped with, as its source reads them."""
        return self.source.temp_c(eventtime), self.source.power(eventtime)

    # --- sample path (from the source, on the reactor) ------------------------
    def process(self, messages):
        """Feed (sequence, payload) pairs from the source to the pipeline
        and hand on what it made."""
        batch = self.pipeline.feed(messages, self.source.timing(), self.motion)
        for window in batch.windows:
            for callback in self.window_callbacks:
                callback(window)
        if self.dump_samples is not None and len(batch.times):
            self.dump_samples.extend(batch.dump_rows())
        if batch.fault_started is not None:
            msg = self.pipeline.fault_message(self.name, batch.fault_started)
            logging.warning(msg)
            self.reactor.register_callback(lambda e: self._act_on_fault(msg))

    def _act_on_fault(self, msg):
        gcode = self.printer.lookup_object('gcode')
        if self.pause_resume is None or not self._is_printing():
            gcode.respond_info(msg)
            return
        gcode.respond_info(msg + ": pausing")
        # Pausing from inside an event needs the pause itself to happen now
        # (send_pause_command); PAUSE then runs the user's macro, if any.
        self.pause_resume.send_pause_command()
        try:
            gcode.run_script("PAUSE")
        except Exception:
            logging.exception("flow_sensor %s: PAUSE failed", self.name)

    def _is_printing(self):
        # A sensor that faults on an idle printer (unplugged at boot) must
        # not run PAUSE: act only while printing, as filament sensors do.
        idle_timeout = self.printer.lookup_object('idle_timeout')
        now = self.reactor.monotonic()
        return idle_timeout.get_status(now)['state'] == 'Printing'

    # --- status and dump endpoint ---------------------------------------------
    def get_status(self, eventtime=None):
        # Built when the pipeline's status (held until new data) or the
        # source's simulation facts change, not per poll (as heaters.py)
        parts = (self.pipeline.status(), self.source.simulation)
        if self.status_parts is None or any(
                a is not b for a, b in zip(parts, self.status_parts)):
            self.status_parts = parts
            self.status = dict(parts[0], simulation=parts[1])
        return self.status

    def _dump_start(self):
        self.dump_samples = []

    def _dump_stop(self):
        self.dump_samples = None

    def _dump_batch(self, eventtime):
        # what has arrived since the last decode batch too: a client's newest
        # sample is then as old as the MCU's message and the link make it
        self.source.catch_up()
        if not self.dump_samples:
            return {}
        data, self.dump_samples = self.dump_samples, []
        status = self.pipeline.status()
        return {'data': data, 'grip': status['grip'], 'fault': status['fault'],
                'errors': status['errors']}

    # --- commands --------------------------------------------------------------
    cmd_QUERY_FLOW_SENSOR_help = "Report grip, flows and errors of a flow sensor"

    def cmd_QUERY_FLOW_SENSOR(self, gcmd):
        self.source.sync()
        s = self.pipeline.status()
        grip = "not judged" if s['grip'] is None else f"{s['grip']:.3f}"
        position = s['filament_position']
        position = "none" if position is None else f"{position:.3f} mm"
        gcmd.respond_info(
            f"flow_sensor {self.name}: grip {grip},"
            f" measured flow {s['measured_flow']:.2f} mm^3/s,"
            f" commanded flow {s['commanded_flow']:.2f} mm^3/s,"
            f" filament position {position}, {s['sample_rate']:.0f} samples/s,"
            f" errors {s['errors'] or 'none'}, fault {s['fault'] or 'none'}")

    def _wait_for_samples(self, print_time):
        """Sensor filament (counts / counts_per_mm) once samples reach
        print_time; the toolhead must be idle (after wait_moves)."""
        deadline = self.reactor.monotonic() + SAMPLE_WAIT_TIMEOUT
        while True:
            self.source.sync(until=print_time)
            position = self.pipeline.position_at_or_after(print_time)
            if position is not None:
                return position
            if self.pipeline.fault:
                raise self.printer.command_error(
                    f"flow_sensor {self.name}: fault '{self.pipeline.fault}'")
            now = self.reactor.monotonic()
            if now > deadline:
                raise self.printer.command_error(
                    f"flow_sensor {self.name}: no samples from the sensor")
            self.reactor.pause(now + 0.020)

    def _measure_extrusion(self, length, speed):
        """(commanded mm, sensor mm) of one extrude-only move."""
        toolhead = self.toolhead
        toolhead.wait_moves()
        # A sample period on: after a calibration (which drops the sensor's
        # position) a batch-mode twin has a new sample before the move.
        toolhead.dwell(self.sample_period)
        start = toolhead.get_last_move_time()
        sensor0 = self._wait_for_samples(start)
        pos = toolhead.get_position()
        pos[3] += length
        toolhead.move(pos, speed)
        # G-code's idea of where the extruder is follows the move: else the
        # next G1 E starts from before it and feeds nothing
        self.printer.lookup_object("gcode_move").reset_last_position()
        end = toolhead.get_last_move_time()
        toolhead.wait_moves()
        sensor1 = self._wait_for_samples(end)
        find = self.extruder.find_past_position
        return find(end) - find(start), sensor1 - sensor0

    def _check_extruder(self, gcmd):
        toolhead_extruder = self.toolhead.get_extruder()
        if toolhead_extruder is not self.extruder:
            raise gcmd.error(f"flow_sensor {self.name} watches {self.extruder_name};"
                             " activate it first")

    cmd_CALIBRATE_FLOW_SENSOR_help = (
        "Extrude at slow speeds and set sensor mm per extruder mm")

    def cmd_CALIBRATE_FLOW_SENSOR(self, gcmd):
        # every parameter read and checked before the first extrusion
        low, high = sensor_cal.CALIBRATION_LENGTH_RANGE
        length = number(gcmd, 'LENGTH', sensor_cal.CALIBRATION_LENGTH_MM,
                        minimum=low, maximum=high)
        try:
            speeds = sensor_cal.parse_speeds(
                gcmd.get('SPEEDS', sensor_cal.DEFAULT_CALIBRATION_SPEEDS))
        except FlowloopError as e:
            raise gcmd.error(f"CALIBRATE_FLOW_SENSOR: {e}; nothing changed") \
                from None
        low, high = sensor_cal.MAX_CALIBRATION_SPREAD_RANGE
        max_spread = number(gcmd, 'MAX_SPREAD', sensor_cal.MAX_CALIBRATION_SPREAD,
                            minimum=low, maximum=high)
        self._check_extruder(gcmd)
        commanded, measured = [], []
        for i, speed in enumerate(speeds):
            gcmd.respond_info(
                f"flow_sensor {self.name}: extruding {length:g} mm at {speed:g}"
                f" mm/s ({i + 1} of {len(speeds)}, about {length / speed:.0f} s)")
            c, m = self._measure_extrusion(length, speed)
            commanded.append(c)
            measured.append(m)
        try:
            fit = sensor_cal.fit_calibration(speeds, commanded, measured, max_spread)
        except sensor_cal.ReversedSensor as e:
            raise gcmd.error(self._reversed_message(e)
                             + "; calibration unchanged") from None
        except FlowloopError as e:
            raise gcmd.error(
                f"flow_sensor {self.name}: {e}; calibration unchanged") from None
        old = self.pipeline.calibration
        report = self._set_calibration(fit.calibration)
        gcmd.respond_info("\n".join([
            f"flow_sensor {self.name}: {fit.describe()}",
            f"calibration {old:.5f} -> {fit.calibration:.5f} (in use now)"]
            + report))

    cmd_CALIBRATE_EXTRUDER_ROTATION_DISTANCE_help = (
        "Correct the extruder rotation_distance from what the sensor measured")

    def cmd_CALIBRATE_EXTRUDER_ROTATION_DISTANCE(self, gcmd):
        low, high = sensor_cal.ROTATION_DISTANCE_LENGTH_RANGE
        length = number(gcmd, 'LENGTH', sensor_cal.ROTATION_DISTANCE_LENGTH_MM,
                        minimum=low, maximum=high)
        low, high = sensor_cal.CALIBRATION_SPEED_RANGE
        speed = number(gcmd, 'SPEED', sensor_cal.ROTATION_DISTANCE_SPEED_MM_S,
                       minimum=low, maximum=high)
        self._check_extruder(gcmd)
        stepper = self.extruder.extruder_stepper.stepper
        old_rd = stepper.get_rotation_distance()[0]
        gcmd.respond_info(f"flow_sensor {self.name}: extruding {length:g} mm at"
                          f" {speed:g} mm/s (about {length / speed:.0f} s)")
        commanded, measured = self._measure_extrusion(length, speed)
        try:
            change = sensor_cal.rotation_distance_correction(
                old_rd, commanded, measured)
        except sensor_cal.ReversedSensor as e:
            raise gcmd.error(self._reversed_message(e)
                             + "; nothing changed") from None
        except FlowloopError as e:
            raise gcmd.error(f"flow_sensor {self.name}: {e}; nothing changed") from None
        gcode = self.printer.lookup_object('gcode')
        gcode.run_script_from_command(
            f"SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER={self.extruder_name}"
            f" DISTANCE={change.rotation_distance:.6f}")
        old_cal = self.pipeline.calibration
        report = self._set_calibration(change.calibration, [
            (self.extruder_name, 'rotation_distance',
             f"{change.rotation_distance:.6f}")])
        gcmd.respond_info("\n".join([
            f"flow_sensor {self.name}: commanded {commanded:.3f} mm, sensor"
            f" measured {measured:.3f} mm (ratio {change.ratio:.5f})",
            f"{self.extruder_name} rotation_distance {old_rd:.6f} ->"
            f" {change.rotation_distance:.6f}, sensor calibration"
            f" {old_cal:.5f} -> {change.calibration:.5f} (in use now)"]
            + report))

    def _reversed_message(self, error):
        other = 'reverse' if self.direction_sign > 0 else 'forward'
        return (f"flow_sensor {self.name}: {error}; set direction: {other}"
                f" in [{self.section}]")

    def _set_calibration(self, calibration, also_stage=()):
        """Use a new calibration now and stage it (with also_stage) for
        SAVE_CONFIG; return the report: what to paste, what SAVE_CONFIG keeps."""
        self.pipeline.set_calibration(calibration)
        host = self.printer.lookup_object('flowloop')
        staged, paste = host.stage_for_save_config(
            [(self.section, 'calibration', f"{calibration:.6f}")]
            + list(also_stage))
        return klipper_config.save_report(staged, paste)


class ExtruderMotion(fl_pipeline.Motion):
    """What the pipeline asks of the printer: the watched extruder's
    commanded and planned filament, and the hotend's temperature."""

    def __init__(self, sensor):
        self.sensor = sensor

    def commanded_at(self, times):
        return flow_grip.positions_at(times,
                                      self.sensor.extruder.find_past_position)

    def planned_moves(self, start, end):
        ffi_main, ffi_lib = chelper.get_ffi()
        trapq = self.sensor.extruder.get_trapq()
        moves, end = [], end + 1e-9
        while trapq is not None:
            data = ffi_main.new('struct pull_move[64]')
            count = ffi_lib.trapq_extract_old(trapq, data, len(data), start, end)
            moves.extend((m.print_time, m.move_t, m.start_v, m.accel,
                          m.start_x, m.x_r) for m in data[0:count])
            if count < len(data):
                break
            end = data[count - 1].print_time
        return moves

    def temp_c(self):
        sensor = self.sensor
        return sensor.source.temp_c(sensor.reactor.monotonic())


SOURCES = {'ems22': Ems22Source}
number = flowloop_host.gcode_number


def load_config_prefix(config):
    if config.get('sensor_type', None) == 'simulated':
        raise klipper_config.option_error(
            config, 'sensor_type', klipper_config.simulated_sensor_moved(
                config.get_name()))
    return FlowSensor(config, config.getchoice('sensor_type', SOURCES))
