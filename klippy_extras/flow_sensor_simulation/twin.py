# [flow_sensor_simulation NAME]: a host-side twin of the EMS22
# (flowloop.sensor.twin) that turns the extruder stepper's real steps into
# the payloads an MCU would send, fed to the same pipeline as the real
# sensor's (flow_sensor's FlowSensor); registered as [flow_sensor NAME] too,
# with SET_FLOW_SENSOR_SIMULATION (the package's __init__ loads it).
#
# This file may be distributed under the terms of the GNU GPLv3 license.
# flow_sensor first: it imports the shared module, which turns a requirement
# of the core missing from klippy's Python into a config error
from ..flow_sensor import FlowSensor

# isort: split
from flowloop.control.hotend import HotendModel, HotendParams
from flowloop.errors import FlowloopError
from flowloop.host.klipper_config import finite_float, option_error
from flowloop.material.profile import FlowLine, profile_line
from flowloop.sensor import grip as flow_grip
from flowloop.sensor import pipeline as fl_pipeline
from flowloop.sensor import twin

if (__package__ or '').startswith('klippy.'):
    # Kalico loads flowloop as the package klippy.plugins: its chelper is
    # klippy.chelper (one FFI with the toolhead's trapq)
    from ... import chelper
else:   # Klipper's klippy/extras/
    import chelper

PLANNED_NEVER = 1e99   # print time past every planned move


def load_simulated_sensor(config):
    """The flow sensor [flow_sensor NAME] on the twin, for the section
    [flow_sensor_simulation NAME]."""
    section = config.get_name()
    sensor_name = 'flow_sensor ' + section.split()[-1]
    if config.has_section(sensor_name):
        raise config.error(
            f"Section [{section}]: [{sensor_name}] exists too; a simulated"
            f" sensor and a real one need names of their own")
    sensor = FlowSensor(config, SimulatedSource)
    config.get_printer().add_object(sensor_name, sensor)
    source = sensor.source
    sensor.register_command('SET_FLOW_SENSOR_SIMULATION',
                            source.cmd_SET_FLOW_SENSOR_SIMULATION,
                            source.cmd_SET_FLOW_SENSOR_SIMULATION_help, config)
    return sensor


# The twin heater's options besides heater_power: HotendParams' fields
HOTEND_OPTIONS = (('heater_time_constant', 'time_constant_s'),
                  ('heater_heat_capacity', 'heat_capacity_j_per_c'))


class SimulatedSource:
    """A host-side twin of the sensor: at each step generation it turns the
    extruder stepper's motion into the bytes an MCU would send."""

    def __init__(self, config, sensor):
        self.sensor = sensor
        self.printer = config.get_printer()
        self.mcu = self.printer.lookup_object('mcu')
        default = twin.DEFAULT_MELT_LINE
        melt_temp = finite_float(config, 'melt_temp', 200.)
        melt = FlowLine(
            slope_mm3_s_per_c=finite_float(config, 'melt_slope',
                                           default.slope_mm3_s_per_c, above=0.),
            temp_c=melt_temp,
            flow_mm3_s=finite_float(config, 'melt_flow',
                                    default.flow_mm3_s(melt_temp), above=0.))
        low, high = twin.MELT_SCALE_RANGE
        self.melt_scale = finite_float(config, 'melt_scale', 1., minval=low,
                                       maxval=high)
        low, high = twin.SENSOR_SCALE_RANGE
        lag_low, lag_high = twin.MELT_TIME_RANGE
        self.twin = twin.SimulatedEms22(
            twin.scaled_line(melt.line(), self.melt_scale),
            counts_per_mm=sensor.counts_per_mm,
            sensor_scale=finite_float(config, 'sensor_scale', 1., minval=low,
                                      maxval=high),
            noise_counts=finite_float(config, 'noise_counts',
                                      twin.DEFAULT_NOISE_COUNTS, minval=0.),
            spi_mode=sensor.spi_mode, seed=config.getint('seed', 0),
            melt_time_s=finite_float(config, 'melt_time',
                                     twin.DEFAULT_MELT_TIME_S,
                                     minval=lag_low, maxval=lag_high),
            hotend=self._hotend(config))
        # The extruder's real rotation_distance (default: as configured)
        self.true_rotation_distance = finite_float(
            config, 'true_rotation_distance', None, above=0.)
        self.start_clock = None
        self.rest_ticks = self.time_shift = 0
        self.stepper = self.heater = None
        self.steps = None     # StepClock: how far the extruder's steps are final
        self.realtime = False
        self.mm_per_step = 0.
        self.simulation = None
        self.printer.register_event_handler('flowloop:profile_activated',
                                            self._handle_profile)
        self.printer.register_event_handler('flowloop:heater_fixed_power',
                                            self._handle_fixed_power)

    @staticmethod
    def _hotend(config):
        # With heater_power the twin's nozzle heats, lags and sags
        # (flowloop.control.hotend); without it it is at its target at once.
        # heater_time_constant and heater_heat_capacity make it slower or
        # heavier (a high-mass hotend); they describe that heater only.
        power = finite_float(config, 'heater_power', None)
        shape = {
            'heater_time_constant': finite_float(
                config, 'heater_time_constant', None, above=0.),
            'heater_heat_capacity': finite_float(
                config, 'heater_heat_capacity', None, above=0.)}
        if power is None:
            for option, value in shape.items():
                if value is not None:
                    raise option_error(config, option,
                                       "needs heater_power (the twin has no"
                                       " heater without it)")
            return None
        params = {name: shape[option] for option, name in HOTEND_OPTIONS
                  if shape[option] is not None}
        try:
            return HotendModel(HotendParams(max_power_w=power, **params))
        except FlowloopError as e:
            raise option_error(config, 'heater_power', str(e)) from None

    def _handle_profile(self, extruder, profile, working_point):
        # The twin melts what the active profile's line says (one melt line)
        if extruder == self.sensor.extruder_name and profile is not None:
            self.catch_up()
            self.twin.melt = twin.scaled_line(
                profile_line(profile, working_point), self.melt_scale)

    def _handle_fixed_power(self, extruder, power):
        # A fixed-power measurement holds the twin's heater at power (0..1 of
        # heater_power), or gives it back to its controller (None).
        hotend = self.twin.hotend
        if extruder == self.sensor.extruder_name and hotend is not None:
            self.catch_up()
            hotend.fixed_power_w = (None if power is None
                                    else power * hotend.params.max_power_w)

    def connect(self, sensor):
        extruder = sensor.extruder
        area = getattr(extruder, 'filament_area', None)
        if area:
            self.twin.filament_area_mm2 = area
        self.heater = sensor.heater
        self.steps = StepClock(self.printer, sensor.toolhead, self._flush)
        self.stepper = extruder.extruder_stepper.stepper
        rotation_distance, steps_per_rotation = \
            self.stepper.get_rotation_distance()
        true_rd = self.true_rotation_distance or rotation_distance
        self.mm_per_step = true_rd / steps_per_rotation

    def start(self):
        self.rest_ticks = self.mcu.seconds_to_clock(self.sensor.sample_period)
        # The twin samples from now on (no motion can be older)
        print_time = self.mcu.estimated_print_time(
            self.printer.get_reactor().monotonic())
        self.start_clock = self.mcu.print_time_to_clock(print_time)
        # Batch mode reports print time 0 for ever; a paced batch-mode klippy
        # (devtools/realtime_klippy.py) lets it follow the clock: then the twin
        # samples as real time passes and is the heater's thermometer.
        self.realtime = self.mcu.is_fileoutput() and print_time > 0.
        self.simulation = {'clock': self.steps.kind, 'realtime': self.realtime}

    def timing(self):
        return fl_pipeline.SampleTiming(self.start_clock, self.rest_ticks,
                                        self.time_shift,
                                        self.mcu.clock_to_print_time)

    def temp_c(self, eventtime):
        # The twin's nozzle: its hotend model's, else at its target at once
        return self.twin.temp_c(self.heater.get_status(eventtime)['target'])

    def hotend_params(self):
        hotend = self.twin.hotend
        return None if hotend is None else hotend.params

    def power(self, eventtime):
        hotend = self.twin.hotend
        if hotend is None:
            return self.heater.get_status(eventtime)['power']
        return hotend.power_w / hotend.params.max_power_w

    def _flush(self):
        # Runs as the host generates steps (before the new ones are final)
        self.catch_up()

    def catch_up(self, until=None):
        """Samples up to where the extruder's steps are final; up to `until`
        (inclusive) if the caller waited for the moves (nothing is queued
        beyond). In real time, never beyond now."""
        if self.start_clock is None:
            return
        done_time = self._planned_until(self.steps.final_until())
        if until is not None:
            done_time = max(done_time, until + 1e-9)
        now = None
        if self.realtime:
            now = self.mcu.estimated_print_time(self.printer.get_reactor()
                                                .monotonic())
            done_time = now if self.steps.idle() else min(done_time, now)
        times = fl_pipeline.due_times(self.timing(), self.twin.next_index,
                                      done_time)
        if times:
            # Filament the stepper really fed: its steps times the true mm/step
            steps = self.stepper.get_past_mcu_position
            fed = [steps(t) * self.mm_per_step for t in times]
            # The heater's target: the nozzle's temperature, or its hotend's goal
            target_c = self.heater.get_status(None)['target']
            self.sensor.process(self.twin.messages(times, fed, target_c))
        if now is not None:
            # No MCU measures this heater: the twin's nozzle is its reading
            self.heater.temperature_callback(now, self.temp_c(None))

    def _planned_until(self, done_time):
        """No later than the extruder's planned E position can be read (the
        sensor tells pressure advance from a retraction by it): Kalico's
        trapq_extract_old reads only moves finalized into the history,
        Klipper's the queued ones too."""
        ffi_main, ffi_lib = chelper.get_ffi()
        data = ffi_main.new('struct pull_move[1]')
        extruder = self.sensor.extruder
        if not ffi_lib.trapq_extract_old(extruder.get_trapq(), data, 1, 0.,
                                         PLANNED_NEVER):
            return done_time
        m = data[0]
        end = m.print_time + m.move_t
        end_mm = float(flow_grip.trapq_positions(
            [(m.print_time, m.move_t, m.start_v, m.accel, m.start_x, m.x_r)],
            [end])[0])
        if abs(end_mm - extruder.last_position) < 1e-6:
            return done_time    # nothing planned beyond what can be read
        return min(done_time, end)

    def sync(self, until=None):
        # In batch mode steps are generated only when the reactor gets to
        # its flush timer, which a G-code batch never yields to: generate
        # them now so the twin can follow the motion queued so far. In real
        # time the samples come as the clock passes the motion.
        if self.mcu.is_fileoutput() and not self.realtime:
            self.sensor.toolhead.flush_step_generation()
        self.catch_up(until)

    def set_fault(self, fault):
        """The twin misbehaves from now on (None: it stops); FlowloopError
        names an unknown fault."""
        self.catch_up()
        self.twin.set_fault(fault)

    cmd_SET_FLOW_SENSOR_SIMULATION_help = "Make the simulated sensor misbehave"

    def cmd_SET_FLOW_SENSOR_SIMULATION(self, gcmd):
        fault = gcmd.get('FAULT', 'none').lower()
        try:
            self.set_fault(None if fault == 'none' else fault)
        except FlowloopError as e:
            raise gcmd.error(str(e)) from None
        gcmd.respond_info(
            f"flow_sensor {self.sensor.name}: simulated fault {fault}")


class StepClock:
    """How far the extruder's steps (and its trapq history) are final, on
    either host: Klipper's motion_queuing (2025-08 on) calls flush callbacks,
    Kalico's toolhead calls step generators. Either way the callback runs
    before that round's steps are final, so the round before it counts."""

    def __init__(self, printer, toolhead, on_flush):
        self.on_flush = on_flush
        self.generated = 0.
        motion_queuing = printer.lookup_object('motion_queuing', None)
        if motion_queuing is not None:
            self.kind, self.flusher = 'motion_queuing', motion_queuing
            motion_queuing.register_flush_callback(
                lambda flush_time, step_gen_time: self._round(step_gen_time))
        else:
            # Registered after the extruder's own: runs once its steps exist
            self.kind, self.flusher = 'step_generator', toolhead
            toolhead.register_step_generator(self._round)

    def _round(self, step_gen_time):
        self.on_flush()
        self.generated = max(self.generated, step_gen_time)

    def final_until(self):
        # Steps are final to the last flush; the trapq history (the planned
        # E position) to the last generation less the scan window.
        flusher = self.flusher
        return min(flusher.last_flush_time,
                   self.generated - flusher.kin_flush_delay)

    def idle(self):
        """Nothing is queued beyond the final steps (the position holds)."""
        return self.flusher.need_flush_time <= self.flusher.last_flush_time
