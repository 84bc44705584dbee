# [measure_profile]'s executor: one MEASURE_MATERIAL_PROFILE on the
# printer. The procedure (flowloop.material.procedure) says what to do next;
# Run does it: the heater's control swapped for a fixed power and given
# back, turns on the G-code queue shared with the console, extrusion into
# air, temperature readings and what the sensor saw.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import contextlib
import logging

from flowloop.host.fixed_power import FixedPowerControl
from flowloop.material import procedure as fl_proc

HEARTBEAT_INTERVAL = 0.5
TURN_PAUSE_S = 0.001        # the reactor's moment between two turns
SLEEP_S = 0.1               # longest pause while the printer runs a step
NAME = fl_proc.NAME


class MeasurementStopped(Exception):
    """The run ends early: nothing is stored."""


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
        self.pwm = None     # while held at a fixed power
        self.status_key = self.last_status = None   # status(), when built
        self.heartbeat_timer = self.reactor.register_timer(
            self._heartbeat, self.reactor.NOW)

    def status(self):
        """The run's status: the procedure's progress, the heater's control;
        a new one only when one of them changed."""
        key = (self._status, self.procedure.progress, self.control_name(),
               self.pwm)
        if key != self.status_key:
            self.status_key = key
            self.last_status = self._status.with_progress(
                key[1]).with_heater(key[2], key[3])
        return self.last_status

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
        self.pwm = pwm

    def restore_heater(self):
        """Give the heater its own control back (idempotent; any thread)."""
        if self.old_control is None:
            return
        self.heater.set_control(self.old_control)
        self.old_control = self.control = self.pwm = None
        self.printer.send_event('flowloop:heater_fixed_power',
                                self.extruder_name, None)

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
            self.extruder_name, self.procedure.stop_reason, paused, self.left,
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
        run queued (console commands meanwhile need not wait a step). Only
        on a paced printer: in batch mode print time runs ahead of any clock."""
        mcu = self.printer.lookup_object('mcu')
        while not self.procedure.stop_reason:
            now = self.reactor.monotonic()
            left = print_time - mcu.estimated_print_time(now)
            if left <= 0.:
                return
            self.reactor.pause(now + min(left, SLEEP_S))

    def _wait(self):
        self.toolhead.wait_moves()
        self.sensor.sync(self.toolhead.get_last_move_time())
