# [measure_profile]: MEASURE_MATERIAL_PROFILE measures a material profile's
# into-air line with the flow sensor (ddPrint's procedure): for each level
# the heater is held at a fixed power, the extruder pushes filament into air
# at a rising flow until the grip falls below MIN_GRIP, and the lines fitted
# to those points are handed to Moonraker (flowloop_store_profile).
#
# The command starts the run and returns, as SDCARD_PRINT_FILE starts a
# print: a reactor timer drives the levels and steps and takes the G-code
# queue to queue each step (and each temperature reading) and to read what
# the sensor saw, not while the printer runs it, so what is typed in the
# console (CANCEL_MATERIAL_PROFILE, M112) runs in between. A command in
# between that moves the toolhead, changes the extruder heater's target or
# control, or PAUSE, ends the run as a cancel does.
#
# The fixed power is a heater control object swapped in as PID_CALIBRATE
# swaps its own, and given back on every way out (success, error,
# CANCEL_MATERIAL_PROFILE, shutdown, restart). What to do next, the
# settling, step judging, retries, fits, refusals and status are decided in
# flowloop (material.procedure, with material.measure, material.fit,
# control.watchdog and host.fixed_power); this module does it on the printer.
#
# This module is the section (commands, status, the hand-over to Moonraker);
# run.py carries out a run's actions on the printer.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import collections
import logging

# The shared module first: it turns a requirement of the core missing from
# klippy's Python into a config error
from .. import flowloop as flowloop_host

# isort: split
from flowloop.control import watchdog
from flowloop.errors import FlowloopError
from flowloop.host import klipper_config
from flowloop.host.klipper_config import option_error
from flowloop.material import measure as fl_measure
from flowloop.material import procedure as fl_proc
from flowloop.material import profile as fl_profile
from flowloop.numbers import parse_numbers
from flowloop.sensor import grip as flow_grip

# A package (this file and run.py): klippy/extras/measure_profile/ on
# Klipper, klippy/plugins/measure_profile/ on Kalico
from .run import MeasurementStopped, Run

number = flowloop_host.gcode_number
integer = flowloop_host.gcode_integer

STORE_METHOD = "flowloop_store_profile"
NAME = fl_proc.NAME
PRINT_NAME = fl_proc.PRINT_NAME


class MeasureProfile:
    def __init__(self, config):
        self.printer = printer = config.get_printer()
        self.host = printer.load_object(config, 'flowloop')
        self.reactor = printer.get_reactor()
        self.sensor_name = config.get('sensor', None)
        low, high = fl_measure.STEP_TIME_RANGE_S
        step_time = config.getfloat(
            'step_time', fl_measure.DEFAULT_STEP_TIME_S, minval=low, maxval=high)
        low, high = fl_measure.SETTLE_TIME_RANGE_S
        settle_time = config.getfloat(
            'settle_time', fl_measure.DEFAULT_SETTLE_TIME_S, minval=low,
            maxval=high)
        low, high = fl_measure.MAX_SETTLE_TIME_RANGE_S
        max_settle_time = config.getfloat(
            'max_settle_time', fl_measure.DEFAULT_MAX_SETTLE_TIME_S, minval=low,
            maxval=high)
        self.host_timeout = config.getfloat(
            'host_timeout', watchdog.DEFAULT_HOST_TIMEOUT_S, minval=1.,
            maxval=60.)
        try:
            self.settings = fl_proc.Settings(step_time, settle_time,
                                             max_settle_time, config.get_name())
        except FlowloopError as e:
            raise option_error(config, 'max_settle_time', str(e)) from None
        self.run = None              # the measurement in progress, or None
        self.watch = None            # a print being watched, or None
        self.status = fl_proc.Status()
        printer.register_event_handler('klippy:connect', self._handle_connect)
        printer.register_event_handler('klippy:shutdown', self._handle_shutdown)
        printer.register_event_handler('klippy:disconnect',
                                       self._handle_disconnect)
        gcode = printer.lookup_object('gcode')
        gcode.register_command('MEASURE_MATERIAL_PROFILE',
                               self.cmd_MEASURE_MATERIAL_PROFILE,
                               desc=self.cmd_MEASURE_MATERIAL_PROFILE_help)
        gcode.register_command('MEASURE_MATERIAL_PROFILE_PRINT',
                               self.cmd_MEASURE_MATERIAL_PROFILE_PRINT,
                               desc=self.cmd_MEASURE_MATERIAL_PROFILE_PRINT_help)
        gcode.register_command('MEASURE_MATERIAL_PROFILE_LAYER',
                               self.cmd_MEASURE_MATERIAL_PROFILE_LAYER,
                               desc=self.cmd_MEASURE_MATERIAL_PROFILE_LAYER_help)
        gcode.register_command('CANCEL_MATERIAL_PROFILE',
                               self.cmd_CANCEL_MATERIAL_PROFILE,
                               desc=self.cmd_CANCEL_MATERIAL_PROFILE_help)
        # The same as CANCEL_MATERIAL_PROFILE, for clients that do not type
        printer.lookup_object('webhooks').register_endpoint(
            'measure_profile/cancel', self._handle_cancel_request)

    def get_status(self, eventtime=None):
        run = self.run
        return (self.status if run is None else run.status()).as_dict()

    # --- grip windows (every flow sensor; the run keeps its own sensor's) ----
    def _handle_connect(self):
        for sensor in klipper_config.flow_sensors(self.printer):
            sensor.subscribe_grip_windows(
                lambda window, sensor=sensor: self._handle_window(sensor,
                                                                  window))

    def _handle_window(self, sensor, window):
        # In the reactor, possibly inside a flush: only collect and decide;
        # what follows runs in its own callback.
        run = self.run
        if run is not None and run.sensor is sensor:
            run.procedure.window(window)
        watch = self.watch
        if watch is None or watch.sensor is not sensor:
            return
        found = watch.measurement.window(window)
        if found is None:
            return
        self.watch = None
        if isinstance(found, fl_proc.Stop):
            self.reactor.register_callback(
                lambda e: self._end_watch(found.reason))
        else:
            self.reactor.register_callback(
                lambda e: self._finish_print(watch, found))

    # --- cancel and shutdown -------------------------------------------------
    cmd_CANCEL_MATERIAL_PROFILE_help = (
        "Stop a running MEASURE_MATERIAL_PROFILE or _PRINT (nothing is"
        " stored)")

    def cmd_CANCEL_MATERIAL_PROFILE(self, gcmd):
        what = self._cancel("CANCEL_MATERIAL_PROFILE")
        if what is None:
            gcmd.respond_info("CANCEL_MATERIAL_PROFILE: no measurement running")
        elif what is self.run:
            gcmd.respond_info(f"CANCEL_MATERIAL_PROFILE: {NAME} stops (the"
                              " extrusion queued runs out); nothing is stored")

    def _handle_cancel_request(self, web_request):
        cancelled = self._cancel("measure_profile/cancel")
        web_request.send({'cancelled': cancelled is not None})

    def _cancel(self, how):
        """Cancel a watch at once, a run at its next reading or turn; which
        one it was (None: nothing runs)."""
        watch, run = self.watch, self.run
        if watch is not None:
            self.watch = None
            self._end_watch(f"cancelled ({how}); nothing stored")
            return watch
        if run is not None:
            run.procedure.cancel(f"cancelled ({how})")
        return run

    def _handle_shutdown(self):
        if self.run is not None:
            self.run.procedure.shutdown()
        self._handle_disconnect()

    def _handle_disconnect(self):
        if self.run is not None:
            self.run.restore_heater()

    # --- the command ---------------------------------------------------------
    cmd_MEASURE_MATERIAL_PROFILE_help = (
        "Measure a material profile's into-air line with the flow sensor:"
        " NAME= EXTRUDER= TEMPS= or POWERS= START_FLOW= STEP= MAX_FLOW="
        " MIN_GRIP= [ACTIVATE=1] [MIN_TEMP= MAX_TEMP=]")

    def cmd_MEASURE_MATERIAL_PROFILE(self, gcmd):
        sdcard = self.printer.lookup_object('virtual_sdcard', None)
        pause_resume = self.printer.lookup_object('pause_resume', None)
        self._refuse(gcmd, NAME,
                     printing=sdcard is not None and sdcard.is_active(),
                     paused=pause_resume is not None and pause_resume.is_paused)
        self.run = run = self._prepare(gcmd)
        levels = len(run.procedure.plan.levels)
        gcmd.respond_info(f"{NAME}: started ({levels} levels);"
                          " CANCEL_MATERIAL_PROFILE stops it")
        # As virtual_sdcard runs a print: the command returns, a timer runs
        self.reactor.register_callback(lambda e: self._run(run))

    def _refuse(self, gcmd, command, **state):
        busy = self.run is not None or self.watch is not None
        refusal = fl_proc.start_refusal(busy, **state)
        if refusal:
            raise gcmd.error(f"{command}: {refusal}")

    def _prepare(self, gcmd):
        """Everything checked before anything changes (bad input: one line)."""
        name = gcmd.get('NAME')
        extruder_name = gcmd.get('EXTRUDER', 'extruder')
        min_temp = number(gcmd, 'MIN_TEMP', None, **fl_proc.TEMP_PARAM)
        max_temp = number(gcmd, 'MAX_TEMP', None, **fl_proc.TEMP_PARAM)
        start_flow = number(gcmd, 'START_FLOW', None, **fl_proc.FLOW_PARAM)
        step = number(gcmd, 'STEP', fl_measure.DEFAULT_STEP_MM3_S,
                      **fl_proc.FLOW_PARAM)
        max_flow = number(gcmd, 'MAX_FLOW', fl_measure.DEFAULT_MAX_FLOW_MM3_S,
                          **fl_proc.FLOW_PARAM)
        min_grip = number(gcmd, 'MIN_GRIP', None, **fl_proc.MIN_GRIP_PARAM)
        activate = integer(gcmd, 'ACTIVATE', 0, **fl_proc.SWITCH_PARAM)
        try:
            fl_profile.check_name(name)
            extruder, heater = self._extruder(extruder_name)
            sensor = self._sensor(extruder_name)
            base = self._base(extruder_name)
            bounds = fl_proc.bounds_for(base, min_temp, max_temp,
                                        heater.max_temp, heater.min_temp)
            plan = fl_measure.make_plan(
                self._levels(gcmd.get('TEMPS', None), 'TEMPS'),
                self._levels(gcmd.get('POWERS', None), 'POWERS'),
                start_flow, step, max_flow,
                fl_profile.min_grip_of(base, min_grip),
                bounds.min_temp_c, bounds.max_temp_c, heater.get_max_power())
            limits, rules = watchdog.for_measurement(bounds, self.host_timeout)
            toolhead = self.printer.lookup_object('toolhead')
            fl_proc.check_active(extruder_name,
                                 toolhead.get_extruder() is extruder)
        except FlowloopError as e:
            raise gcmd.error(f"{NAME}: {e}; nothing changed") from None
        procedure = fl_proc.Procedure(name, plan, bounds, self.settings, base,
                                      _hardware(extruder, heater), rules)
        return Run(self.printer, procedure, self.status.running(name),
                   extruder_name, heater, sensor, limits, bool(activate))

    def _run(self, run):
        gcode = self.printer.lookup_object('gcode')
        error = None
        try:
            done = run.measure()
            logging.info("%s: %s", NAME, "; ".join(done.fitted.lines()))
        except (MeasurementStopped, FlowloopError) as e:
            error = f"{NAME}: {e}; nothing stored"
        except Exception:
            logging.exception("%s: internal error", NAME)
            error = f"{NAME}: internal error (see klippy.log); nothing stored"
        finally:
            run.finish()
            self.run = None
        self.status = run.status().with_heater(run.control_name())
        if error is not None:
            self.status = self.status.aborted(error)
            _respond_error(gcode, error)
            return
        self._deliver(NAME, done, 'into_air', run.extruder_name, run.activate,
                      _respond_error)

    def _deliver(self, command, done, kind, extruder_name, activate, failed):
        """Say what was measured and hand the profile to Moonraker (its
        failure said by failed(gcode, message)); the status follows."""
        gcode = self.printer.lookup_object('gcode')
        for line in done.lines:
            gcode.respond_info(f"{command}: {line}")
        profile = done.profile
        self.status = self.status.measured(done, kind)
        try:
            self.printer.lookup_object('webhooks').call_remote_method(
                STORE_METHOD, profile=fl_profile.profile_to_dict(profile),
                activate_extruder=extruder_name if activate else None)
        except self.printer.command_error as e:
            message = fl_proc.not_stored(command, profile.name, str(e))
            self.status = self.status.not_stored(message)
            failed(gcode, message)
            return
        message = fl_proc.handed_over(command, profile.name, extruder_name,
                                      activate)
        self.status = self.status.stored(message)
        gcode.respond_info(message)

    # --- the real-print measurement ------------------------------------------
    cmd_MEASURE_MATERIAL_PROFILE_PRINT_help = (
        "Watch a print of the measurement part (flowloop measure-part) and"
        " store the real-print line where grip falls: NAME= [EXTRUDER=]"
        " [MIN_GRIP=] [ACTIVATE=1]")

    def cmd_MEASURE_MATERIAL_PROFILE_PRINT(self, gcmd):
        self._refuse(gcmd, PRINT_NAME)
        name = gcmd.get('NAME')
        extruder_name = gcmd.get('EXTRUDER', 'extruder')
        activate = bool(integer(gcmd, 'ACTIVATE', 0, **fl_proc.SWITCH_PARAM))
        min_grip = number(gcmd, 'MIN_GRIP', None, **fl_proc.MIN_GRIP_PARAM)
        try:
            fl_profile.check_name(name)
            extruder, heater = self._extruder(extruder_name)
            sensor = self._sensor(extruder_name)
            fl_proc.check_sensor(sensor.name, sensor.get_status()['fault'])
            base = fl_proc.print_base(self._base(extruder_name))
            measurement = fl_proc.PrintMeasurement(
                name, base, min_grip, _hardware(extruder, heater))
        except FlowloopError as e:
            raise gcmd.error(f"{PRINT_NAME}: {e}; nothing changed") from None
        self.watch = PrintSession(measurement, extruder_name, sensor, activate)
        self.status = self.status.watching(name,
                                           f"{PRINT_NAME}: watching the grip")
        watch = measurement.watch
        gcmd.respond_info(
            f"{PRINT_NAME}: watching {extruder_name}'s grip (median of"
            f" the last {watch.filament_mm:g} mm of filament below"
            f" {watch.min_grip:g} ends it): print"
            " the measurement part now")

    cmd_MEASURE_MATERIAL_PROFILE_LAYER_help = (
        "The planned flow of a measurement part's layer (flowloop"
        " measure-part writes it)")

    def cmd_MEASURE_MATERIAL_PROFILE_LAYER(self, gcmd):
        integer(gcmd, 'LAYER', **fl_proc.LAYER_PARAM)   # the file's own count
        flow = number(gcmd, 'FLOW', **fl_proc.FLOW_PARAM)
        if self.watch is not None:
            # The layer's moves begin after those queued so far
            start = self.printer.lookup_object('toolhead').get_last_move_time()
            self.watch.measurement.add_layer(start, flow)

    def _end_watch(self, why):
        message = f"{PRINT_NAME}: {why}"
        self.status = self.status.aborted(message)
        self.printer.lookup_object('gcode').respond_info(message)

    def _finish_print(self, session, step):
        gcode = self.printer.lookup_object('gcode')
        outcome = session.measurement.finish(step)
        for line in outcome.notes:
            gcode.respond_info(f"{PRINT_NAME}: {line}")
        if isinstance(outcome, fl_proc.Stop):
            self._end_watch(outcome.reason)
            return
        self._deliver(PRINT_NAME, outcome, 'real_print', session.extruder_name,
                      session.activate, lambda gcode, message:
                      gcode.respond_info(message))
        self._stop_print(gcode)

    def _stop_print(self, gcode):
        # The part has done its job: end the print, only while printing
        idle_timeout = self.printer.lookup_object('idle_timeout')
        now = self.reactor.monotonic()
        if idle_timeout.get_status(now)['state'] != 'Printing':
            return
        try:
            gcode.run_script("CANCEL_PRINT")
        except Exception:
            logging.exception("%s: CANCEL_PRINT failed", PRINT_NAME)

    # --- lookups -------------------------------------------------------------
    @staticmethod
    def _levels(text, param):
        if text is None:
            return None
        return parse_numbers(text, param, what="level")

    def _extruder(self, name):
        extruder = None
        if fl_profile.is_extruder_name(name):
            extruder = klipper_config.find_extruder(self.printer, name)
        if extruder is None:
            raise FlowloopError(f"EXTRUDER: no extruder named '{name}'")
        return extruder, extruder.get_heater()

    def _sensor(self, extruder_name):
        sensor = klipper_config.find_flow_sensor(self.printer, extruder_name,
                                                 self.sensor_name)
        if sensor is None:
            raise FlowloopError(fl_proc.missing_sensor(self.sensor_name,
                                                       extruder_name))
        return sensor

    def _base(self, extruder_name):
        """The extruder's active profile, or None."""
        active = self.host.get_active_profile(extruder_name)
        return None if active is None else active.profile


def _hardware(extruder, heater):
    return fl_proc.Hardware(
        filament_area_mm2=extruder.filament_area,
        nozzle_diameter_mm=extruder.nozzle_diameter,
        max_power=heater.get_max_power(), window_mm=flow_grip.DEFAULT_WINDOW_MM)


# One MEASURE_MATERIAL_PROFILE_PRINT: its decisions, what the watch needs
PrintSession = collections.namedtuple(
    'PrintSession', 'measurement extruder_name sensor activate')


def _respond_error(gcode, message):
    # As Klipper answers a failed command: '!! ' marks it red in the console
    logging.info(message)
    gcode.respond_raw(f"!! {message}")


def load_config(config):
    return MeasureProfile(config)
