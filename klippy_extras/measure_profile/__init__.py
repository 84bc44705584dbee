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
# settling, step judging, retries, fits and status are decided in flowloop
# (material.procedure, with material.measure, material.fit and
# control.watchdog); this module does it on the printer.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import collections
import contextlib
import dataclasses
import functools
import logging

from flowloop.control import watchdog
from flowloop.errors import FlowloopError
from flowloop.host import klipper_config
from flowloop.host.klipper_config import option_error
from flowloop.material import measure as fl_measure
from flowloop.material import procedure as fl_proc
from flowloop.material import profile as fl_profile
from flowloop.numbers import parse_numbers
from flowloop.sensor import grip as flow_grip

HEARTBEAT_INTERVAL = 0.5
TURN_PAUSE_S = 0.001        # the reactor's moment between two turns
SLEEP_S = 0.1               # longest pause while the printer runs a step
STORE_METHOD = "flowloop_store_profile"
NAME = fl_proc.NAME
PRINT_NAME = fl_proc.PRINT_NAME


class MeasurementStopped(Exception):
    """The run ends early: nothing is stored."""


class FixedPowerControl:
    """A heater control that holds one PWM (runs in the heater's thread:
    no reactor or G-code calls). On every reading the watchdog's cutoff
    (flowloop.control.watchdog.FixedPowerCutoff: the temperature and host
    rules) says what power to apply.

    Klipper's heater calls temperature_update and check_busy; Kalico's
    calls more of its control (get_profile, get_type, check_valid,
    update_smooth_time, a second sensor's temperature): those answer as
    Kalico's own calibration controls do, and a host that never calls them
    loses nothing."""
    KIND = 'fixed_power'

    def __init__(self, heater, pwm, limits):
        self.heater = heater
        self.cutoff = watchdog.FixedPowerCutoff(limits, pwm)

    @property
    def stopped(self):
        """Why the power was cut, or None (the reactor reports it)."""
        return self.cutoff.stopped

    def heartbeat(self, print_time):
        """The reactor is alive at print_time."""
        self.cutoff.heartbeat_s = print_time

    def temperature_update(self, read_time, temp, target_temp,
                           secondary_temp=None):
        # (Kalico's dual-sensor heaters pass secondary_temp; not used)
        self.heater.set_pwm(read_time, self.cutoff.power_at(read_time, temp))

    def check_busy(self, eventtime, smoothed_temp, target_temp):
        return False

    # --- what Kalico's heaters ask of a control ------------------------------
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

    def get_status(self, eventtime=None):
        run = self.run
        return (self.status if run is None else run.status()).as_dict()

    def _set_status(self, **changes):
        self.status = dataclasses.replace(self.status, **changes)

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
            self.run.restore_heater()

    # --- the command ---------------------------------------------------------
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
        self.run = run = self._prepare(gcmd)
        levels = len(run.procedure.plan.levels)
        gcmd.respond_info(f"{NAME}: started ({levels} levels);"
                          " CANCEL_MATERIAL_PROFILE stops it")
        # As virtual_sdcard runs a print: the command returns, a timer runs
        self.reactor.register_callback(lambda e: self._run(run))

    def _prepare(self, gcmd):
        """Everything checked before anything changes (bad input: one line)."""
        name = gcmd.get('NAME')
        extruder_name = gcmd.get('EXTRUDER', 'extruder')
        try:
            fl_profile.check_name(name)
            extruder, heater = self._extruder(extruder_name)
            sensor = self._sensor(extruder_name)
            base = self._base(extruder_name)
            bounds = fl_proc.bounds_for(base, gcmd.get_float('MIN_TEMP', None),
                                        gcmd.get_float('MAX_TEMP', None),
                                        heater.max_temp)
            plan = fl_measure.make_plan(
                self._levels(gcmd.get('TEMPS', None), 'TEMPS'),
                self._levels(gcmd.get('POWERS', None), 'POWERS'),
                gcmd.get_float('START_FLOW', None),
                gcmd.get_float('STEP', fl_measure.DEFAULT_STEP_MM3_S),
                gcmd.get_float('MAX_FLOW', fl_measure.DEFAULT_MAX_FLOW_MM3_S),
                fl_profile.min_grip_of(base, gcmd.get_float('MIN_GRIP', None)),
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
        procedure = fl_proc.Procedure(
            name, plan, bounds, self.settings, base,
            _hardware(extruder, heater),
            functools.partial(watchdog.stop_reason, limits))
        status = dataclasses.replace(
            self.status, state='running', name=name, result=None, message='')
        return Run(self.printer, procedure, status, extruder_name, heater,
                   sensor, limits,
                   bool(gcmd.get_int('ACTIVATE', 0, minval=0, maxval=1)))

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
        self.status = dataclasses.replace(run.status(),
                                          heater_control=run.control_name())
        if error is not None:
            self._set_status(state='aborted', message=error)
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
        self._set_status(state='measured', points=done.points,
                         result=fl_proc.Result.of(profile, kind))
        try:
            self.printer.lookup_object('webhooks').call_remote_method(
                STORE_METHOD, profile=fl_profile.profile_to_dict(profile),
                activate_extruder=extruder_name if activate else None)
        except self.printer.command_error as e:
            message = (f"{command}: profile '{profile.name}' measured but not"
                       f" stored ({e}): is Moonraker's [flowloop] component"
                       " loaded?")
            self._set_status(message=message)
            failed(gcode, message)
            return
        message = (f"{command}: profile '{profile.name}' handed to Moonraker"
                   + (f" and activated on {extruder_name}" if activate else ""))
        self._set_status(state='stored', message=message)
        gcode.respond_info(message)

    # --- the real-print measurement ------------------------------------------
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
            extruder, heater = self._extruder(extruder_name)
            sensor = self._sensor(extruder_name)
            base = fl_proc.print_base(self._base(extruder_name))
            measurement = fl_proc.PrintMeasurement(
                name, base, gcmd.get_float('MIN_GRIP', None),
                _hardware(extruder, heater))
        except FlowloopError as e:
            raise gcmd.error(f"{PRINT_NAME}: {e}; nothing changed") from None
        self.watch = PrintSession(measurement, extruder_name, sensor, activate)
        self._set_status(state='watching', name=name, level=None, levels=0,
                         flow=None, points=(), result=None,
                         message=f"{PRINT_NAME}: watching the grip")
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
        layer = gcmd.get_int('LAYER', minval=1)
        flow = gcmd.get_float('FLOW', above=0.)
        if self.watch is not None:
            # The layer's moves begin after those queued so far
            start = self.printer.lookup_object('toolhead').get_last_move_time()
            self.watch.measurement.add_layer(layer, start, flow)

    def _end_watch(self, why):
        message = f"{PRINT_NAME}: {why}"
        self._set_status(state='aborted', message=message)
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


class Run:
    """One MEASURE_MATERIAL_PROFILE on the printer: the procedure's
    actions done (the heater swap, turns, moves, readings)."""

    def __init__(self, printer, procedure, status, extruder_name, heater,
                 sensor, limits, activate):
        self.printer, self.reactor = printer, printer.get_reactor()
        self.procedure, self._status = procedure, status
        self.extruder_name, self.heater, self.sensor = extruder_name, heater, sensor
        self.limits, self.activate = limits, activate
        self.toolhead = printer.lookup_object('toolhead')
        self.gcode = printer.lookup_object('gcode')
        self.mutex = self.gcode.get_mutex()
        self.gcode_move = printer.lookup_object('gcode_move')
        self.pause_resume = printer.lookup_object('pause_resume', None)
        self.left = None    # (position, heater target, control) after a turn
        self.pheaters = printer.lookup_object('heaters')
        self.old_target = heater.get_status(self.reactor.monotonic())['target']
        self.old_control = self.control = None
        self.heartbeat_timer = self.reactor.register_timer(
            self._heartbeat, self.reactor.NOW)

    def status(self):
        """The run's status: the procedure's progress, the heater's control."""
        return self._status.with_progress(self.procedure.progress)

    # --- heater --------------------------------------------------------------
    def _heartbeat(self, eventtime):
        control = self.control
        if control is not None:
            mcu = self.printer.lookup_object('mcu')
            control.heartbeat(mcu.estimated_print_time(eventtime))
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
        self._status = dataclasses.replace(
            self._status, heater_control=self.control_name(), heater_pwm=pwm)

    def restore_heater(self):
        """Give the heater its own control back (idempotent; any thread)."""
        if self.old_control is None:
            return
        self.heater.set_control(self.old_control)
        self.old_control = self.control = None
        self.printer.send_event('flowloop:heater_fixed_power',
                                self.extruder_name, None)
        self._status = dataclasses.replace(
            self._status, heater_control=self.control_name(), heater_pwm=None)

    def _release(self):
        with self._turn(check=False):
            self.restore_heater()

    def control_name(self):
        return type(self.heater.control).__name__

    def finish(self):
        self.restore_heater()
        self.reactor.unregister_timer(self.heartbeat_timer)
        if not self.printer.is_shutdown():
            with self.mutex:
                self.heater.set_temp(self.old_target)
                self.gcode_move.reset_last_position()

    # --- the procedure's actions ---------------------------------------------
    def measure(self):
        """Do the procedure's actions until it is done (its Done);
        MeasurementStopped when it stops or a command in between ends it."""
        procedure = self.procedure
        action = procedure.start()
        try:
            while not isinstance(action, (fl_proc.Done, fl_proc.Stop)):
                action = procedure.send(self._do(action))
        finally:
            if not isinstance(action, fl_proc.Done):
                self._release()
        if isinstance(action, fl_proc.Stop):
            raise MeasurementStopped(action.reason)
        return action

    def _do(self, action):
        """Do one action; the answer the procedure expects (or None)."""
        kind = type(action)
        if kind is fl_proc.Say:
            self.gcode.respond_info(f"{NAME}: {action.text}")
        elif kind is fl_proc.Log:
            logging.info("%s: %s", NAME, action.text)
        elif kind is fl_proc.Read:
            return self._reading()
        elif kind is fl_proc.Extrude:
            return self._extrude(action)
        elif kind is fl_proc.Dwell:
            self._on_printer([lambda: self.toolhead.dwell(action.seconds)])
        elif kind is fl_proc.Release:
            self._release()
        else:
            with self._turn():
                if kind is fl_proc.HeatTo:
                    self.pheaters.set_temperature(self.heater, action.temp_c)
                else:
                    self.hold_power(action.pwm)
        return None

    def _extrude(self, action):
        speed = action.speed_mm_s

        def extrude(seconds):
            pos = self.toolhead.get_position()
            pos[3] += speed * seconds
            self.toolhead.move(pos, speed)
        start, end = self._on_printer(
            [lambda s=seconds: extrude(s) for seconds in action.moves_s])
        return fl_proc.Extruded(start, end)

    def _reading(self):
        if self.printer.is_shutdown():
            raise MeasurementStopped("Klipper shut down")
        temp, power = self.sensor.hotend_reading(self.reactor.monotonic())
        now = self.toolhead.get_last_move_time()
        control = self.control
        return fl_proc.Reading(
            now, temp, power, heater_stop=control and control.stopped,
            sensor_fault=self.sensor.get_status()['fault'])

    # --- turns: the run and the console share the G-code queue ---------------
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
        """MeasurementStopped when the run must end before this turn."""
        paused = self.pause_resume is not None and self.pause_resume.is_paused
        reason = fl_proc.turn_stop(
            self.extruder_name, self.procedure.cancel_reason,
            self.printer.is_shutdown(), paused, self.left,
            None if self.left is None else self._state())
        if reason:
            raise MeasurementStopped(reason)

    # --- time and readings ---------------------------------------------------
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
        while not (self.printer.is_shutdown() or self.procedure.cancel_reason):
            now = self.reactor.monotonic()
            left = print_time - mcu.estimated_print_time(now)
            if left <= 0.:
                return
            self.reactor.pause(now + min(left, SLEEP_S))

    def _wait(self):
        self.toolhead.wait_moves()
        self.sensor.sync(self.toolhead.get_last_move_time())


def _respond_error(gcode, message):
    # As Klipper answers a failed command: '!! ' marks it red in the console
    logging.info(message)
    gcode.respond_raw(f"!! {message}")


def load_config(config):
    return MeasureProfile(config)
