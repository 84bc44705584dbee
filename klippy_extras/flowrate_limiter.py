# [flowrate_limiter]: caps the volumetric flow of every extruding G-code
# move, from a fixed max_flow, the active profile at the hotend's
# temperature, the flow sensor's grip (reactive) and a grip model fitted to
# it (predictive).
#
# A move transform (as skew_correction.py): registered at klippy:connect,
# chained to the transform it replaces, so bed mesh, skew correction and
# exclude_object keep working. The caps and the decision live in
# flowloop.control; this module reads config, follows the printer and
# hands each move to the core.
#
# On a toolchanger or IDEX machine, one section per extruder, named as
# Klipper names per-tool sections ([tmc2209 extruder1]): [flowrate_limiter]
# for `extruder`, [flowrate_limiter extruder1] for extruder1. One transform
# (klippy_extras/flowloop.py ToolMoves) hands each move to the section of
# the extruder that prints; SET_/QUERY_FLOWRATE_LIMIT take EXTRUDER=.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
# The shared module first: it turns a requirement of the core missing from
# klippy's Python into a config error
from . import flowloop as flowloop_host

# isort: split
from flowloop.control import caps as fl_caps
from flowloop.control import limiter as fl_limiter
from flowloop.control.hotend import nozzle_estimate_for
from flowloop.errors import FlowloopError
from flowloop.host.klipper_config import (
    extruder_for,
    find_flow_sensor,
    option_error,
    option_message,
)

SETTING_FIELDS = {'max_flow': 'max_flow_mm3_s', 'mode': 'mode',
                  'min_grip': 'min_grip', 'min_speed_factor': 'min_speed_factor',
                  'hysteresis': 'hysteresis', 'recovery_rate': 'recovery_per_s',
                  'climb_from': 'climb_from'}



class FlowrateLimiter:
    def __init__(self, config):
        self.printer = printer = config.get_printer()
        self.host = printer.load_object(config, 'flowloop')
        self.reactor = printer.get_reactor()
        self.section = config.get_name()
        self.extruder_name = (flowloop_host.named_tool(config, 'flowrate_limiter')
                              or config.get('extruder', 'extruder'))
        self.control_option = flowloop_host.heater_control_option(
            config, self.extruder_name)
        self.sensor_name = config.get('sensor', None)
        # option -> LimiterSettings field; the limits live in flowloop.control
        values = {'max_flow': config.getfloat('max_flow', None),
                  'mode': config.get('mode', fl_limiter.DEFAULT_MODE),
                  'min_grip': config.getfloat('min_grip', None),
                  'min_speed_factor': config.getfloat('min_speed_factor', None),
                  'hysteresis': config.getfloat('hysteresis', None),
                  'recovery_rate': config.getfloat('recovery_rate', None),
                  'climb_from': config.getfloat('climb_from', None)}
        settings = {}
        for option, value in values.items():
            if value is None:
                continue
            field = SETTING_FIELDS[option]
            try:
                fl_limiter.LimiterSettings(**{field: value})
            except FlowloopError as e:
                raise option_error(config, option, str(e)) from None
            settings[field] = value
        self.settings = fl_limiter.LimiterSettings(**settings)
        self.limiter = None
        self.next_transform = None
        self.toolhead = self.heater = self.sensor = self.mcu = None
        self.nozzle = None   # the nozzle estimate where none is measured
        printer.register_event_handler('klippy:connect', self._handle_connect)
        printer.register_event_handler('flowloop:profile_activated',
                                       self._handle_profile)
        self.tools = self.host.tool_moves('flowrate_limiter')
        if self.tools.add(config, self.extruder_name, self):
            # one command for every tool: EXTRUDER= names it
            gcode = printer.lookup_object('gcode')
            gcode.register_command('SET_FLOWRATE_LIMIT',
                                   self.cmd_SET_FLOWRATE_LIMIT,
                                   desc=self.cmd_SET_FLOWRATE_LIMIT_help)
            gcode.register_command('QUERY_FLOWRATE_LIMIT',
                                   self.cmd_QUERY_FLOWRATE_LIMIT,
                                   desc=self.cmd_QUERY_FLOWRATE_LIMIT_help)
            # nozzle health (Moonraker asks at each job's start and end)
            printer.lookup_object('webhooks').register_endpoint(
                'flowrate_limiter/nozzle_evidence',
                self._handle_nozzle_evidence)

    # --- setup ---------------------------------------------------------------
    def _handle_connect(self):
        self.extruder = extruder = extruder_for(self.printer, self.section,
                                                self.extruder_name)
        self.heater = extruder.get_heater()
        self.toolhead = self.printer.lookup_object('toolhead')
        self.mcu = self.printer.lookup_object('mcu')
        self.filament_area = extruder.filament_area
        self.limiter = fl_limiter.FlowLimiter(
            self.settings, self.filament_area,
            host=flowloop_host.host_facts(self.printer, self.heater,
                                          self.control_option))
        self.sensor = self._find_sensor()
        if self.sensor is not None:
            self.sensor.subscribe_grip_windows(self._handle_window)
        # batch mode: the thermal model follows the heater's target, on the
        # simulated sensor's hotend if it has one (as a thermistor would
        # read that hotend on a printer)
        self.nozzle = nozzle_estimate_for(
            self.mcu.is_fileoutput(),
            self.mcu.estimated_print_time(self.reactor.monotonic()),
            None if self.sensor is None else self.sensor.simulated_hotend())
        active = self.host.get_active_profile(self.extruder_name)
        if active is not None:
            self.limiter.set_profile(*active)
        self.tools.join(self)

    def _find_sensor(self):
        sensor = find_flow_sensor(self.printer, self.extruder_name,
                                  self.sensor_name)
        if sensor is None and self.sensor_name is not None:
            raise self.printer.config_error(option_message(
                self.section, 'sensor', f"no [flow_sensor {self.sensor_name}]"))
        return sensor

    def _handle_profile(self, extruder, profile, working_point):
        if extruder == self.extruder_name and self.limiter is not None:
            # with the melt ratio the activation brought (the event keeps
            # the arguments every section takes)
            active = self.host.get_active_profile(extruder)
            self.limiter.set_profile(profile, working_point,
                                     None if active is None else active.melt_ratio)

    def _handle_window(self, window):
        # In the reactor, possibly inside a flush: no pauses here. A window
        # says whether the sensor is faulted (Window.faulted, Window.fault).
        self.limiter.on_window(window)


    # --- the moves of this extruder (ToolMoves hands them over) --------------
    def move(self, newpos, speed):
        # Runs per G-code move: only what this move needs (make bench
        # measures klippy's host time with and without it).
        # From where the toolhead really is: commands that move it directly
        # (calibrations) leave no stale start behind.
        start = self.next_transform.get_position()
        shape = fl_caps.move_shape(start, newpos)
        if self.nozzle is None and shape.extrude_mm > 0.:
            # A printer (or a klippy paced to the clock): the toolhead may
            # pause inside each piece's move, windows and temperatures
            # arrive meanwhile, and the next piece is capped by them
            count = self.limiter.pieces(shape, speed)
            if count > 1:
                for end in fl_caps.piece_ends(start, newpos, count):
                    self._queue(fl_caps.move_shape(start, end), end, speed)
                    start = end
                return
        self._queue(shape, newpos, speed)

    def _queue(self, shape, newpos, speed):
        melted_mm3 = 0.
        if shape.extrude_mm > 0.:   # ToolMoves hands this tool's moves only
            if self.nozzle is None:
                temp_c, _ = self.heater.get_temp(self.reactor.monotonic())
                self.limiter.set_temperature(temp_c)
            speed = self.limiter.limit(shape, speed)
            melted_mm3 = shape.extrude_mm * self.filament_area
        if self.nozzle is not None:
            # Batch mode: the models run on the moves' own (cruise) time,
            # the idle tools' too (they melt nothing meanwhile)
            duration_s = shape.duration_s(speed)
            for member in self.tools.members():
                member.pass_time(duration_s,
                                 melted_mm3 if member is self else 0.)
        self.next_transform.move(newpos, speed)

    def pass_time(self, duration_s, melted_mm3):
        if self.nozzle.add_move(duration_s, melted_mm3):
            self.limiter.set_temperature(self.nozzle.read(
                self.heater.get_status(None)['target']))

    # --- status and commands -------------------------------------------------
    def get_status(self, eventtime=None):
        if self.limiter is None:
            return {}
        return self.limiter.status()  # built when it changed

    cmd_SET_FLOWRATE_LIMIT_help = (
        "Turn the flowrate limiter on or off, set its max_flow (mm^3/s) or"
        " its mode")

    def cmd_SET_FLOWRATE_LIMIT(self, gcmd):
        self._tool(gcmd).set_limit(gcmd)

    def _tool(self, gcmd):
        return self.tools.pick(gcmd.get('EXTRUDER', None), gcmd)

    def set_limit(self, gcmd):
        enable = flowloop_host.gcode_integer(gcmd, 'ENABLE', None, minimum=0,
                                             maximum=1)
        max_flow = gcmd.get('MAX_FLOW', None)
        clear = max_flow is not None and max_flow.strip().lower() == 'none'
        if not clear:
            max_flow = flowloop_host.gcode_number(gcmd, 'MAX_FLOW', None,
                                                  above=0.)
        mode = gcmd.get('MODE', None)
        try:
            self.limiter.configure(
                enabled=None if enable is None else bool(enable),
                max_flow_mm3_s=None if clear else max_flow,
                clear_max_flow=clear, mode=mode)
        except FlowloopError as e:
            raise gcmd.error(f"SET_FLOWRATE_LIMIT: {e}; nothing changed") \
                from None
        self.report(gcmd)

    cmd_QUERY_FLOWRATE_LIMIT_help = "Report the flowrate limiter's caps"

    def cmd_QUERY_FLOWRATE_LIMIT(self, gcmd):
        self._tool(gcmd).report(gcmd)

    def _handle_nozzle_evidence(self, web_request):
        """The grip evidence the named extruder's limiter has summed since
        its profile was activated (EXTRUDER-less: the printing tool's);
        flowloop.control.nozzle_health judges it."""
        try:
            member = self.tools.table.pick(
                web_request.get_str('extruder', None), self.tools.active_name())
        except FlowloopError as e:
            raise web_request.error(str(e)) from None
        limiter = member.limiter
        evidence = None if limiter is None else limiter.evidence
        # and what the grip model believes now (the next print's seed)
        web_request.send({'extruder': member.extruder_name,
                          'evidence': None if evidence is None
                          else evidence.to_dict(),
                          'model_melt_ratio': None if limiter is None
                          else limiter.measured_melt_ratio})

    def report(self, gcmd):
        gcmd.respond_info(fl_limiter.status_line(self.section,
                                                 self.limiter.status()))


def load_config(config):
    return FlowrateLimiter(config)


def load_config_prefix(config):
    return FlowrateLimiter(config)
