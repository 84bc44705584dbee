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
# CANCEL_MATERIAL_PROFILE, shutdown, restart). The plan, settling, step judging,
# fits and watchdog rules live in flowloop (material.measure, material.fit,
# control.watchdog); this module drives the printer.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import contextlib
import dataclasses
import logging

from flowloop.control import watchdog
from flowloop.errors import FlowloopError
from flowloop.host.klipper_config import option_message
from flowloop.material import fit as fl_fit
from flowloop.material import measure as fl_measure
from flowloop.material import profile as fl_profile
from flowloop.numbers import parse_numbers
from flowloop.sensor import grip as flow_grip

HEARTBEAT_INTERVAL = 0.5
READING_INTERVAL = 1.0      # s between temperature readings while waiting
MAX_MOVE_TIME = 1.0         # s per extrude-only move of a step
MAX_STEP_RETRIES = 2        # a step without a judged window runs again
TURN_PAUSE_S = 0.001        # the reactor's moment between two turns
SLEEP_S = 0.1               # longest pause while the printer runs a step
STORE_METHOD = "flowloop_store_profile"
NAME = "MEASURE_MATERIAL_PROFILE"
PRINT_NAME = "MEASURE_MATERIAL_PROFILE_PRINT"


class MeasurementStopped(Exception):
    """The run ends early: nothing is stored."""


class FixedPowerControl:
    """A heater control that holds one PWM (runs in the heater's thread:
    no reactor or G-code calls). On every reading it applies the watchdog's
    temperature and host rules and cuts the power if one says stop.

    Klipper's heater calls temperature_update and check_busy; Kalico's
    calls more of its control (get_profile, get_type, check_valid,
    update_smooth_time, a second sensor's temperature): those answer as
    Kalico's own calibration controls do, and a host that never calls them
    loses nothing."""
    KIND = 'fixed_power'

    def __init__(self, heater, pwm, limits):
        self.heater = heater
        self.pwm = pwm
        self.limits = limits
        self.heartbeat = None    # print time of the reactor's last heartbeat
        self.stopped = None      # why the power was cut (the reactor reports)

    def temperature_update(self, read_time, temp, target_temp,
                           secondary_temp=None):
        # (Kalico's dual-sensor heaters pass secondary_temp; not used)
        if self.stopped is None:
            self.stopped = (watchdog.temperature_stop(self.limits, temp)
                            or watchdog.host_stop(self.limits, read_time,
                                                  self.heartbeat))
        self.heater.set_pwm(read_time, 0. if self.stopped else self.pwm)

    def check_busy(self, eventtime, smoothed_temp, target_temp):
        return False

    # --- what Kalico's heaters ask of a control --------------------------------
    def get_profile(self):
        # Not a PID profile: PID_PROFILE SAVE refuses it, GET lists it
        return {'name': self.KIND, 'control': self.KIND}

    def get_type(self):
        return self.KIND

    def check_valid(self):
        pass     # a fixed power needs no model constants

    def update_smooth_time(self, *args):
        pass     # no smoothing: the power is fixed


class MeasureProfile:
    def __init__(self, config):
        self.printer = printer = config.get_printer()
        self.host = printer.load_object(config, 'flowloop')
        self.reactor = printer.get_reactor()
        self.section = config.get_name()
        self.sensor_name = config.get('sensor', None)
        low, high = fl_measure.STEP_TIME_RANGE_S
        self.step_time = config.getfloat(
            'step_time', fl_measure.DEFAULT_STEP_TIME_S, minval=low, maxval=high)
        low, high = fl_measure.SETTLE_TIME_RANGE_S
        self.settle_time = config.getfloat(
            'settle_time', fl_measure.DEFAULT_SETTLE_TIME_S, minval=low,
            maxval=high)
        low, high = fl_measure.MAX_SETTLE_TIME_RANGE_S
        self.max_settle_time = config.getfloat(
            'max_settle_time', fl_measure.DEFAULT_MAX_SETTLE_TIME_S, minval=low,
            maxval=high)
        self.host_timeout = config.getfloat(
            'host_timeout', watchdog.DEFAULT_HOST_TIMEOUT_S, minval=1.,
            maxval=60.)
        if self.max_settle_time < self.settle_time:
            raise config.error(option_message(
                self.section, 'max_settle_time',
                f"{self.max_settle_time:g} is below settle_time"
                f" {self.settle_time:g}"))
        self.run = None              # the measurement in progress, or None
        self.watch = None            # a print being watched, or None
        self.cancel_reason = None
        self.status = {}
        self._set_status('idle')
        printer.register_event_handler('klippy:connect', self._handle_connect)
        printer.register_event_handler('klippy:shutdown', self._handle_shutdown)
        printer.register_event_handler('klippy:disconnect',
                                       self._handle_shutdown)
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

    # --- status ---------------------------------------------------------------
    def _set_status(self, state, **changes):
        status = dict(self.status, state=state, **changes)
        for field in ('name', 'level', 'flow'):
            status.setdefault(field, None)
        status.setdefault('levels', 0)
        status.setdefault('message', '')
        status.setdefault('points', [])
        status.setdefault('result', None)
        status.setdefault('heater_control', None)
        status.setdefault('heater_pwm', None)
        self.status = status

    def get_status(self, eventtime=None):
        return self.status

    # --- grip windows (every flow sensor; the run keeps its own sensor's) ------
    def _handle_connect(self):
        for name, sensor in self.printer.lookup_objects('flow_sensor'):
            if name.startswith('flow_sensor '):
                sensor.subscribe_grip_windows(
                    lambda window, sensor=sensor: self._handle_window(sensor,
                                                                      window))

    def _handle_window(self, sensor, window):
        # In the reactor, possibly inside a flush: only collect and decide;
        # what follows runs in its own callback.
        run = self.run
        if run is not None and run.sensor is sensor:
            run.windows.append(window)
        watch = self.watch
        if watch is None or watch.sensor is not sensor:
            return
        if window.reason == 'fault':
            self.watch = None
            self.reactor.register_callback(lambda e: self._end_watch(
                "flow sensor fault: nothing stored"))
            return
        step = watch.watch.add(window)
        if step is not None:
            self.watch = None
            self.reactor.register_callback(
                lambda e: self._finish_print(watch, step))

    # --- cancel and shutdown ----------------------------------------------------
    cmd_CANCEL_MATERIAL_PROFILE_help = (
        "Stop a running MEASURE_MATERIAL_PROFILE or _PRINT (nothing is"
        " stored)")

    def cmd_CANCEL_MATERIAL_PROFILE(self, gcmd):
        if self.watch is not None:
            self.watch = None
            self._end_watch("cancelled (CANCEL_MATERIAL_PROFILE); nothing"
                            " stored")
            return
        if self.run is None:
            gcmd.respond_info("CANCEL_MATERIAL_PROFILE: no measurement running")
            return
        self.cancel_reason = "cancelled (CANCEL_MATERIAL_PROFILE)"
        gcmd.respond_info(f"CANCEL_MATERIAL_PROFILE: {NAME} stops (the"
                          " extrusion queued runs out); nothing is stored")

    def _handle_cancel_request(self, web_request):
        running = self.run is not None or self.watch is not None
        if self.watch is not None:
            self.watch = None
            self._end_watch("cancelled (measure_profile/cancel); nothing"
                            " stored")
        elif running:
            self.cancel_reason = "cancelled (measure_profile/cancel)"
        web_request.send({'cancelled': running})

    def _handle_shutdown(self):
        if self.run is not None:
            self.run.restore_heater()

    # --- the command ------------------------------------------------------------
    cmd_MEASURE_MATERIAL_PROFILE_help = (
        "Measure a material profile's into-air line with the flow sensor:"
        " NAME= EXTRUDER= TEMPS= or POWERS= START_FLOW= STEP= MAX_FLOW="
        " MIN_GRIP= [ACTIVATE=1] [MIN_TEMP= MAX_TEMP=]")

    def cmd_MEASURE_MATERIAL_PROFILE(self, gcmd):
        if self.run is not None or self.watch is not None:
            raise gcmd.error(f"{NAME}: a measurement is running already")
        sdcard = self.printer.lookup_object('virtual_sdcard', None)
        if sdcard is not None and sdcard.is_active():
            raise gcmd.error(f"{NAME}: a print is running; nothing changed")
        pause_resume = self.printer.lookup_object('pause_resume', None)
        if pause_resume is not None and pause_resume.is_paused:
            raise gcmd.error(f"{NAME}: the printer is paused (RESUME or"
                             " CLEAR_PAUSE first); nothing changed")
        run = self._prepare(gcmd)
        self.run, self.cancel_reason = run, None
        self._set_status('running', name=run.name, level=None,
                         levels=len(run.plan.levels), flow=None, points=[],
                         result=None, message='')
        gcmd.respond_info(f"{NAME}: started ({len(run.plan.levels)} levels);"
                          " CANCEL_MATERIAL_PROFILE stops it")
        # As virtual_sdcard runs a print: the command returns, a timer runs
        self.reactor.register_callback(lambda e: self._run(run))

    def _run(self, run):
        gcode = self.printer.lookup_object('gcode')
        error = None
        try:
            points = run.measure()
            profile, fitted = run.result(points)
        except (MeasurementStopped, FlowloopError) as e:
            error = f"{NAME}: {e}; nothing stored"
        except Exception:
            logging.exception("%s: internal error", NAME)
            error = f"{NAME}: internal error (see klippy.log); nothing stored"
        finally:
            run.finish()
            self.run = None
        if error is not None:
            self._set_status('aborted', message=error,
                             heater_control=run.control_name())
            _respond_error(gcode, error)
            return
        for line in fitted.lines():
            gcode.respond_info(f"{NAME}: {line}")
        self._set_status('measured', heater_control=run.control_name(),
                         result=self._result_status(profile))
        try:
            gcode.respond_info(self._hand_over(NAME, profile, run.extruder_name,
                                               run.activate))
        except self.printer.command_error as e:
            _respond_error(gcode, str(e))

    def _result_status(self, profile, kind='into_air'):
        line = getattr(profile.lines, kind)
        return {'name': profile.name,
                'slope_mm3_s_per_c': line.slope_mm3_s_per_c,
                'temp_c': line.temp_c, 'flow_mm3_s': line.flow_mm3_s,
                'note': profile.provenance.note}

    def _hand_over(self, command, profile, extruder_name, activate):
        """Send the profile to Moonraker; the message (status follows)."""
        webhooks = self.printer.lookup_object('webhooks')
        try:
            webhooks.call_remote_method(
                STORE_METHOD, profile=fl_profile.profile_to_dict(profile),
                activate_extruder=extruder_name if activate else None)
        except self.printer.command_error as e:
            message = (f"{command}: profile '{profile.name}' measured but not"
                       f" stored ({e}): is Moonraker's [flowloop] component"
                       " loaded?")
            self._set_status('measured', message=message)
            raise self.printer.command_error(message) from None
        message = (f"{command}: profile '{profile.name}' handed to Moonraker"
                   + (f" and activated on {extruder_name}" if activate else ""))
        self._set_status('stored', message=message)
        return message

    # --- the real-print measurement ----------------------------------------------
    cmd_MEASURE_MATERIAL_PROFILE_PRINT_help = (
        "Watch a print of the measurement part (flowloop measure-part) and"
        " store the real-print line where grip falls: NAME= [EXTRUDER=]"
        " [MIN_GRIP=] [ACTIVATE=1]")

    def cmd_MEASURE_MATERIAL_PROFILE_PRINT(self, gcmd):
        if self.run is not None or self.watch is not None:
            raise gcmd.error(f"{PRINT_NAME}: a measurement is running already")
        name = gcmd.get('NAME')
        extruder_name = gcmd.get('EXTRUDER', 'extruder')
        activate = bool(gcmd.get_int('ACTIVATE', 0, minval=0, maxval=1))
        try:
            fl_profile.check_name(name)
            extruder, _ = self._extruder(extruder_name)
            sensor = self._sensor(extruder_name)
            base = self.host.get_active_profile(extruder_name)
            if base is None:
                raise FlowloopError(
                    "activate the material's profile first: its into-air line"
                    " gives the real-print line's slope")
            base = base.profile
            watch = fl_measure.PrintWatch(gcmd.get_float(
                'MIN_GRIP', self._default_min_grip(base)))
        except FlowloopError as e:
            raise gcmd.error(f"{PRINT_NAME}: {e}; nothing changed") from None
        self.watch = PrintSession(name, extruder_name, extruder, sensor, base,
                                  watch, activate)
        self._set_status('watching', name=name, level=None, levels=0,
                         flow=None, points=[], result=None,
                         message=f"{PRINT_NAME}: watching the grip")
        gcmd.respond_info(
            f"{PRINT_NAME}: watching {extruder_name}'s grip (median of"
            f" the last {watch.filament_mm:g} mm of filament below"
            f" {watch.min_grip:g} ends it): print"
            " the measurement part now")

    cmd_MEASURE_MATERIAL_PROFILE_LAYER_help = (
        "The planned flow of a measurement part's layer (flowloop"
        " measure-part writes it)")

    def cmd_MEASURE_MATERIAL_PROFILE_LAYER(self, gcmd):
        layer = gcmd.get_int('LAYER', minval=1)
        flow = gcmd.get_float('FLOW', above=0.)
        if self.watch is not None:
            # The layer's moves begin after those queued so far
            start = self.printer.lookup_object('toolhead').get_last_move_time()
            self.watch.layers.append((start, flow))
            self.watch.layer = layer

    def _end_watch(self, why):
        message = f"{PRINT_NAME}: {why}"
        self._set_status('aborted', message=message)
        self.printer.lookup_object('gcode').respond_info(message)

    def _finish_print(self, session, step):
        gcode = self.printer.lookup_object('gcode')
        melted = fl_measure.melted_flow(session.watch.recent, session.layers)
        if melted is not None:
            step = dataclasses.replace(step, measured_mm3_s=melted)
        else:
            gcode.respond_info(
                f"{PRINT_NAME}: no MEASURE_MATERIAL_PROFILE_LAYER in the file:"
                " the flow is the windows' own, low by their travel and"
                " corners (print a part from flowloop measure-part)")
        point = fl_measure.limit_point(step, None, 0., kind='real_print')
        base = session.base
        try:
            fitted = fl_fit.one_point_lines(
                'real_print', point, base.lines.into_air.slope_mm3_s_per_c)
            area = session.extruder.filament_area
            profile = fl_fit.measured_profile(
                session.name, base, fitted, [point], base.bounds,
                base.identity.nozzle_diameter_mm,
                round((4. * area / 3.141592653589793) ** .5, 3),
                session.watch.min_grip, PRINT_NAME)
        except FlowloopError as e:
            self._end_watch(f"{e}; nothing stored")
            return
        gcode.respond_info(
            f"{PRINT_NAME}: grip {step.grip:.3f} at {point.flow_mm3_s:.2f}"
            f" mm^3/s, {point.temp_c:.1f} degC: "
            + fitted.lines()[0])
        self._set_status('measured', points=[
            {'temp_c': point.temp_c, 'flow_mm3_s': point.flow_mm3_s,
             'grip': point.grip, 'heater_pwm': None}],
            result=self._result_status(profile, 'real_print'))
        try:
            gcode.respond_info(self._hand_over(PRINT_NAME, profile,
                                               session.extruder_name,
                                               session.activate))
        except self.printer.command_error as e:
            gcode.respond_info(str(e))
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

    def _prepare(self, gcmd):
        """Everything checked before anything changes (bad input: one line)."""
        name = gcmd.get('NAME')
        extruder_name = gcmd.get('EXTRUDER', 'extruder')
        try:
            fl_profile.check_name(name)
            extruder, heater = self._extruder(extruder_name)
            sensor = self._sensor(extruder_name)
            base = self.host.get_active_profile(extruder_name)
            base = None if base is None else base.profile
            bounds = self._bounds(gcmd, base, heater)
            plan = fl_measure.make_plan(
                self._levels(gcmd.get('TEMPS', None), 'TEMPS'),
                self._levels(gcmd.get('POWERS', None), 'POWERS'),
                gcmd.get_float('START_FLOW', None),
                gcmd.get_float('STEP', fl_measure.DEFAULT_STEP_MM3_S),
                gcmd.get_float('MAX_FLOW', fl_measure.DEFAULT_MAX_FLOW_MM3_S),
                gcmd.get_float('MIN_GRIP', self._default_min_grip(base)),
                bounds.min_temp_c, bounds.max_temp_c)
            limits = watchdog.WatchdogLimits(
                min_temp_c=bounds.min_temp_c, max_temp_c=bounds.max_temp_c,
                host_timeout_s=self.host_timeout)
        except FlowloopError as e:
            raise gcmd.error(f"{NAME}: {e}; nothing changed") from None
        toolhead = self.printer.lookup_object('toolhead')
        if toolhead.get_extruder() is not extruder:
            raise gcmd.error(f"{NAME}: {extruder_name} is not the active"
                             f" extruder (activate it first); nothing changed")
        return Run(self, name, extruder_name, extruder, heater, sensor,
                   base, bounds, plan, limits,
                   bool(gcmd.get_int('ACTIVATE', 0, minval=0, maxval=1)))

    @staticmethod
    def _levels(text, param):
        if text is None:
            return None
        return parse_numbers(text, param, what="level")

    @staticmethod
    def _default_min_grip(base):
        return fl_profile.min_grip_of(base)

    def _extruder(self, name):
        extruder = None
        if fl_profile.is_extruder_name(name):
            extruder = self.printer.lookup_object(name, None)
        if extruder is None or not hasattr(extruder, 'get_heater'):
            raise FlowloopError(f"EXTRUDER: no extruder named '{name}'")
        return extruder, extruder.get_heater()

    def _sensor(self, extruder_name):
        sensors = [obj for name, obj in self.printer.lookup_objects('flow_sensor')
                   if name.startswith('flow_sensor ')]
        for sensor in sensors:
            if self.sensor_name is not None:
                if sensor.name == self.sensor_name:
                    return sensor
            elif sensor.extruder_name == extruder_name:
                return sensor
        which = (f"[flow_sensor {self.sensor_name}]" if self.sensor_name
                 else f"a [flow_sensor] on {extruder_name}")
        raise FlowloopError(f"EXTRUDER: {which} is needed to judge grip")

    @staticmethod
    def _bounds(gcmd, base, heater):
        """The profile's bounds (the active one's, else MIN_TEMP=/MAX_TEMP=),
        never above the heater's max_temp."""
        min_temp = gcmd.get_float('MIN_TEMP', None)
        max_temp = gcmd.get_float('MAX_TEMP', None)
        if base is not None:
            b = base.bounds
            min_temp = b.min_temp_c if min_temp is None else min_temp
            max_temp = b.max_temp_c if max_temp is None else max_temp
        if min_temp is None or max_temp is None:
            raise FlowloopError(
                "no active profile on this extruder gives the temperature "
                "limits: activate one, or give MIN_TEMP= and MAX_TEMP=")
        max_temp = min(max_temp, heater.max_temp)
        if not min_temp < max_temp:
            raise FlowloopError(f"MIN_TEMP: {min_temp:g} degC is not below the"
                                f" maximum {max_temp:g} degC")
        recommended = ((min_temp + max_temp) / 2. if base is None
                       else base.bounds.recommended_temp_c)
        return fl_profile.Bounds(
            min_temp_c=min_temp, max_temp_c=max_temp,
            recommended_temp_c=min(max(recommended, min_temp), max_temp))


class PrintSession:
    """One MEASURE_MATERIAL_PROFILE_PRINT: what the watch needs."""

    def __init__(self, name, extruder_name, extruder, sensor, base, watch,
                 activate):
        self.name, self.extruder_name = name, extruder_name
        self.extruder, self.sensor, self.base = extruder, sensor, base
        self.watch, self.activate = watch, activate
        self.layer = None
        self.layers = []   # (print time it starts, planned flow) per layer


class Run:
    """One MEASURE_MATERIAL_PROFILE: the levels, the heater swap, the ramp."""

    def __init__(self, owner, name, extruder_name, extruder, heater,
                 sensor, base, bounds, plan, limits, activate):
        self.owner = owner
        self.printer, self.reactor = owner.printer, owner.reactor
        self.name, self.extruder_name = name, extruder_name
        self.extruder, self.heater, self.sensor = extruder, heater, sensor
        self.base, self.bounds, self.plan = base, bounds, plan
        self.limits, self.activate = limits, activate
        self.toolhead = self.printer.lookup_object('toolhead')
        self.gcode = self.printer.lookup_object('gcode')
        self.mutex = self.gcode.get_mutex()
        self.gcode_move = self.printer.lookup_object('gcode_move')
        self.pause_resume = self.printer.lookup_object('pause_resume', None)
        self.left = None    # (position, heater target, control) after a turn
        self.pheaters = self.printer.lookup_object('heaters')
        self.area = extruder.filament_area
        self.old_target = heater.get_status(self.reactor.monotonic())['target']
        self.windows = []
        self.holds = []     # (mean power, temp) of each POWERS= heating
        self.old_control = self.control = None
        self.heartbeat_timer = self.reactor.register_timer(
            self._heartbeat, self.reactor.NOW)

    # --- heater -----------------------------------------------------------------
    def _heartbeat(self, eventtime):
        control = self.control
        if control is not None:
            mcu = self.printer.lookup_object('mcu')
            control.heartbeat = mcu.estimated_print_time(eventtime)
        return eventtime + HEARTBEAT_INTERVAL

    def hold_power(self, pwm):
        self.control = FixedPowerControl(self.heater, pwm, self.limits)
        self._heartbeat(self.reactor.monotonic())
        self.old_control = self.heater.set_control(self.control)
        # set_pwm drives nothing without a target; at the profile's minimum
        # it also keeps verify_heater watching the floor.
        self.heater.set_temp(self.limits.min_temp_c)
        self.printer.send_event('flowloop:heater_fixed_power',
                                self.extruder_name, pwm)
        self.owner._set_status('running', heater_control=self.control_name(),
                               heater_pwm=pwm)

    def restore_heater(self):
        """Give the heater its own control back (idempotent; any thread)."""
        if self.old_control is None:
            return
        self.heater.set_control(self.old_control)
        self.old_control = self.control = None
        self.printer.send_event('flowloop:heater_fixed_power',
                                self.extruder_name, None)
        self.owner._set_status(self.owner.status['state'],
                               heater_control=self.control_name(),
                               heater_pwm=None)

    def control_name(self):
        return type(self.heater.control).__name__

    def finish(self):
        self.restore_heater()
        self.reactor.unregister_timer(self.heartbeat_timer)
        if not self.printer.is_shutdown():
            with self.mutex:
                self.heater.set_temp(self.old_target)
                self.gcode_move.reset_last_position()

    # --- turns: the run and the console share the G-code queue ----------------------
    @contextlib.contextmanager
    def _turn(self, check=True):
        """Hold the G-code queue for one piece of the run (a step, a
        reading); commands typed meanwhile run before the next one, and
        what they changed ends the run (check=False: giving back)."""
        # Let the reactor read the console and the API (they queue on the
        # mutex, and go first)
        self.reactor.pause(self.reactor.monotonic() + TURN_PAUSE_S)
        with self.mutex:
            if check:
                self._check_between()
            yield
            # G-code moves go on from where the run left the toolhead
            self.gcode_move.reset_last_position()
            self.left = self._state()

    def _state(self):
        target = self.heater.get_temp(self.reactor.monotonic())[1]
        return (tuple(self.toolhead.get_position()), target,
                self.heater.control)

    def _check_between(self):
        """MeasurementStopped when a command since the last turn changed
        what the run relies on."""
        if self.owner.cancel_reason:
            raise MeasurementStopped(self.owner.cancel_reason)
        if self.printer.is_shutdown():
            raise MeasurementStopped("Klipper shut down")
        if self.pause_resume is not None and self.pause_resume.is_paused:
            raise MeasurementStopped("PAUSE cancels a measurement")
        if self.left is None:
            return
        position, target, control = self.left
        now_position, now_target, now_control = self._state()
        if now_position != position:
            raise MeasurementStopped("the toolhead was moved by another"
                                     " command: cancelled")
        if now_target != target:
            raise MeasurementStopped(
                f"{self.extruder_name}'s target was changed by another command"
                f" ({target:g} -> {now_target:g} degC): cancelled")
        if now_control is not control:
            raise MeasurementStopped(
                f"{self.extruder_name}'s heater control was replaced by another"
                " command: cancelled")

    # --- time and readings --------------------------------------------------------
    def _pass_time(self, seconds):
        """Let print time advance (dwell), then read what the sensor saw."""
        self._on_printer([lambda: self.toolhead.dwell(seconds)])

    def _on_printer(self, actions):
        """Run toolhead actions, then read what the sensor saw; the print
        times before and after. On a printer each action is a turn of its
        own (the toolhead holds its caller while it is more than its
        read-ahead in front) and the wait for them is outside the G-code
        queue. In batch mode all is one turn, as one G-code command: print
        time there is not the clock's, and the reactor could flush the
        lookahead between two turns (a stop mid-step)."""
        if not self._paced():
            with self._turn():
                start = self.toolhead.get_last_move_time()
                for action in actions:
                    action()
                end = self.toolhead.get_last_move_time()
                self._wait()
            return start, end
        with self._turn():
            start = self.toolhead.get_last_move_time()
        for action in actions:
            with self._turn():
                action()
        with self._turn():
            end = self.toolhead.get_last_move_time()
        self._sleep_until(end)
        with self._turn():
            self._wait()
        return start, end

    def _paced(self):
        """Print time follows the clock (a printer; not batch mode)."""
        return getattr(self.toolhead, 'can_pause', True)

    def _sleep_until(self, print_time):
        """Wait, the G-code queue free, until the printer has run what the
        run queued (console commands meanwhile need not wait a step)."""
        if not self._paced():
            return   # batch mode: print time runs ahead of any clock
        mcu = self.printer.lookup_object('mcu')
        while not (self.printer.is_shutdown() or self.owner.cancel_reason):
            now = self.reactor.monotonic()
            left = print_time - mcu.estimated_print_time(now)
            if left <= 0.:
                return
            self.reactor.pause(now + min(left, SLEEP_S))

    def _wait(self):
        self.toolhead.wait_moves()
        self.sensor.sync(self.toolhead.get_last_move_time())

    def _reading(self):
        temp, power = self.sensor.hotend_reading(self.reactor.monotonic())
        return self.toolhead.get_last_move_time(), temp, power

    def _check(self, settled_c=None, previous=None):
        """Raise MeasurementStopped when the run must end; the reading."""
        if self.printer.is_shutdown():
            raise MeasurementStopped("Klipper shut down")
        if self.owner.cancel_reason:
            raise MeasurementStopped(self.owner.cancel_reason)
        now, temp, power = self._reading()
        control = self.control
        reason = (control.stopped if control is not None else None) \
            or watchdog.stop_reason(
                self.limits, temp_c=temp, now_s=now, settled_c=settled_c,
                previous=previous,
                sensor_fault=self.sensor.get_status()['fault'])
        if reason:
            raise MeasurementStopped(reason)
        return now, temp, power

    def _say(self, text):
        self.gcode.respond_info(f"{NAME}: {text}")

    # --- the procedure --------------------------------------------------------------
    def measure(self):
        points = []
        for i, level in enumerate(self.plan.levels):
            where = (f"level {i + 1}/{len(self.plan.levels)}"
                     f" ({self.plan.describe_level(level)})")
            self.owner._set_status('running', level=i + 1, flow=None)
            try:
                point = self._level(where, level)
            finally:
                with self._turn(check=False):
                    self.restore_heater()
            points.append(point)
            self.owner._set_status('running', points=[
                {'temp_c': p.temp_c, 'flow_mm3_s': p.flow_mm3_s,
                 'grip': p.grip, 'heater_pwm': p.heater_pwm} for p in points])
            self._say(f"{where}: limit {point.flow_mm3_s:.2f} mm^3/s at"
                      f" {point.temp_c:.1f} degC, grip {point.grip:.3f}")
        return points

    def _level(self, where, level):
        if self.plan.by == "temperature":
            self._say(f"{where}: heating to {level:g} degC")
            pwm = self._heat_and_settle(level)
        else:
            pwm = level * self.heater.get_max_power()
            self._heat_to_power(where, pwm)
        self._say(f"{where}: heater held at {pwm:.1%} power, settling")
        with self._turn():
            self.hold_power(pwm)
        settled_c = self._settle(fixed=True)[-1][1]
        return self._ramp(where, pwm, settled_c)

    def _heat_to_power(self, where, pwm):
        """Heat (the heater's own control) to where pwm holds the nozzle,
        from the powers that held the temperatures so far."""
        if not self.holds:
            recommended = self.bounds.recommended_temp_c
            self._say(f"{where}: heating to {recommended:g} degC for the power"
                      " that holds it")
            self.holds.append((self._heat_and_settle(
                recommended, fl_measure.POWER_LEVEL_WAITS), recommended))
        for _ in range(fl_measure.POWER_LEVEL_TRIES):
            temp_c = fl_measure.power_level_target(
                pwm, self.holds, self.bounds.min_temp_c,
                self.bounds.max_temp_c)
            if temp_c is None:
                return
            self._say(f"{where}: heating to {temp_c:.1f} degC, where"
                      f" {pwm:.1%} power should hold")
            self.holds.append((self._heat_and_settle(
                temp_c, fl_measure.POWER_LEVEL_WAITS), temp_c))

    def _heat_and_settle(self, temp_c, waits=1):
        """Heat with the heater's own control; the mean power that held
        temp_c, over a settle_time after `waits` more once settled (the
        approach's extra power left out)."""
        with self._turn():
            self.pheaters.set_temperature(self.heater, temp_c)
        for _ in range(waits + 1):
            readings = self._settle(fixed=False, target_c=temp_c)
        return sum(p for _, _, p in readings) / len(readings)

    def _settle(self, fixed, target_c=None):
        """Readings (time, temp, power) until the temperature holds still
        (and, heating, is near target_c)."""
        start = None
        readings = []
        while True:
            if fixed:
                now, temp, power = self._check()
            else:
                if self.printer.is_shutdown() or self.owner.cancel_reason:
                    self._check()
                now, temp, power = self._reading()
            start = now if start is None else start
            readings.append((now, temp, power))
            near = target_c is None or abs(temp - target_c) <= \
                fl_measure.SETTLE_BAND_C
            if near and fl_measure.settled([(t, c) for t, c, _ in readings],
                                           self.owner.settle_time):
                return readings
            if now - start > self.owner.max_settle_time:
                raise MeasurementStopped(
                    f"the temperature did not settle within"
                    f" {self.owner.max_settle_time:g} s (at {temp:.1f} degC)")
            self._pass_time(READING_INTERVAL)

    def _ramp(self, where, pwm, settled_c):
        previous = None
        expected = None
        if self.base is not None:
            expected = fl_profile.profile_line(self.base, 1.).flow_mm3_s(
                settled_c)
        start = self.plan.ramp_start(expected)
        for flow in self.plan.flows(start):
            self.owner._set_status('running', flow=flow)
            now, temp, _ = self._check(settled_c, previous)
            previous = (now, temp)
            step = self._step(flow, self.plan.step_windows(flow, expected))
            self._say(f"{where}: {step.describe()}")
            now, temp, _ = self._check(settled_c, previous)
            previous = (now, temp)
            if step.grip < self.plan.min_grip:
                if flow == start and not self.plan.start_given:
                    self._say(f"{where}: the first step slipped already; the"
                              " point is what the hotend melted (a lower"
                              " START_FLOW= confirms it)")
                return fl_measure.limit_point(step, pwm, temp)
        raise MeasurementStopped(
            f"{where}: grip stayed above {self.plan.min_grip:g} up to MAX_FLOW"
            f" {self.plan.max_flow_mm3_s:g} mm^3/s (raise MAX_FLOW)")

    def _step(self, flow, windows):
        """Extrude into air at flow for step_time (at least `windows` grip
        windows); the step judged."""
        speed = flow / self.area
        # The sensor's window length, as its judged windows show it
        window_mm = max([float(w.commanded_mm) for w in self.windows[-8:]
                         if w.grip is not None]
                        or [flow_grip.DEFAULT_WINDOW_MM])
        duration = fl_measure.step_duration_s(self.owner.step_time, flow,
                                              self.area, window_mm, windows)
        chunks = []
        left = duration
        while left > 1e-9:
            chunks.append(min(MAX_MOVE_TIME, left))
            left -= chunks[-1]

        def extrude(seconds):
            pos = self.toolhead.get_position()
            pos[3] += speed * seconds
            self.toolhead.move(pos, speed)
        for _ in range(MAX_STEP_RETRIES + 1):
            first = len(self.windows)
            start, end = self._on_printer(
                [lambda c=chunk: extrude(c) for chunk in chunks])
            step = fl_measure.judge_step(self.windows[first:], start, end, flow)
            if step is not None:
                return dataclasses.replace(step, duration_s=duration)
            logging.info("%s: no judged window in %.3f..%.3f: %s", NAME, start,
                         end, self.windows[first:])
            self._check()   # a sensor fault judges nothing: say that instead
        raise MeasurementStopped(
            f"no grip window was judged at {flow:g} mm^3/s (a longer"
            f" step_time in [{self.owner.section}]?)")

    # --- the result ---------------------------------------------------------------
    def result(self, points):
        fitted = fl_fit.fit_points("into_air", points, fl_measure.PWM_MAX)
        nozzle = getattr(self.extruder, 'nozzle_diameter', 0.4)
        diameter = (4. * self.area / 3.141592653589793) ** .5
        profile = fl_fit.measured_profile(
            self.name, self.base, fitted, points, self.bounds, nozzle,
            round(diameter, 3), self.plan.min_grip, NAME)
        logging.info("%s: %s", NAME, "; ".join(fitted.lines()))
        return profile, fitted


def _respond_error(gcode, message):
    # As Klipper answers a failed command: '!! ' marks it red in the console
    logging.info(message)
    gcode.respond_raw(f"!! {message}")


def load_config(config):
    return MeasureProfile(config)
