# [autotemp]: the hotend temperature set ahead of the flow the G-code will
# demand. AUTOTEMP_FLOW (written into the file by `flowloop annotate` or
# Moonraker's file processor) announces a window of flow; the active
# material profile's line at the working point turns it into a need, and the
# plan against the hotend thermal model (flowloop.control.autotemp) into
# heater targets, set as the motion is generated. A file without
# annotations falls back to the moves Klipper has queued (reactive).
#
# On a toolchanger or IDEX machine, one section per extruder ([autotemp] for
# `extruder`, [autotemp extruder1] for extruder1, as Klipper's per-tool
# sections are named): each drives its tool's heater only while that tool
# prints (flowloop.control.tools: M104 T<n>, the hand-back at a tool change);
# one transform, one M104/M109 take-over and one set of commands serve them
# all (klippy_extras/flowloop.py ToolMoves).
#
# This file may be distributed under the terms of the GNU GPLv3 license.
# The shared module first: it turns a requirement of the core missing from
# klippy's Python into a config error
from . import flowloop as flowloop_host

# isort: split
from flowloop.control import autotemp as fl_autotemp
from flowloop.control import caps as fl_caps
from flowloop.control import tools as fl_tools
from flowloop.control.hotend import HotendParams, heater_reads
from flowloop.errors import FlowloopError
from flowloop.gcode import melt_window as fl_melt_window
from flowloop.host import klipper_config
from flowloop.host.klipper_config import (
    extruder_for,
    option_error,
)
from flowloop.material.active import working_point_arg

DEFAULTS = HotendParams()



class Autotemp:
    def __init__(self, config):
        self.printer = printer = config.get_printer()
        self.host = printer.load_object(config, 'flowloop')
        self.section = config.get_name()
        self.extruder_name = (flowloop_host.named_tool(config, 'autotemp')
                              or config.get('extruder', 'extruder'))
        self.control_option = flowloop_host.heater_control_option(
            config, self.extruder_name)
        self.override_m104 = config.getboolean('override_m104', True)
        enabled = config.getboolean('enable', True)
        values = {'time_constant': ('time_constant_s', config.getfloat(
                      'time_constant', DEFAULTS.time_constant_s)),
                  'dead_time': ('dead_time_s', config.getfloat(
                      'dead_time', DEFAULTS.dead_time_s)),
                  'heater_power': ('max_power_w', config.getfloat(
                      'heater_power', DEFAULTS.max_power_w))}
        params = {}
        for option, (field, value) in values.items():
            try:
                HotendParams(**{field: value})
            except FlowloopError as e:
                raise option_error(config, option, str(e)) from None
            params[field] = value
        # read by the annotator (flowloop annotate --printer-cfg, Moonraker's
        # upload processor), not here: checked as it reads it
        self.melt_window = klipper_config.finite_float(
            config, 'melt_window', fl_melt_window.MELT_TIME_S,
            minval=fl_melt_window.MIN_MELT_S, maxval=fl_melt_window.MAX_MELT_S)
        wp = config.get('working_point', None)
        try:
            self.working_point = None if wp is None else working_point_arg(wp)
        except FlowloopError as e:
            raise option_error(config, 'working_point', str(e)) from None
        self.params = HotendParams(**params)
        self.core = fl_autotemp.Autotemp(self.params, enabled=enabled)
        self.heater = self.toolhead = self.extruder = None
        self.next_transform = None
        # the last M104/M109 target asked for this tool: its heater's at a
        # tool change (flowloop.control.tools.hand_back_target)
        self.user_target_c = None
        printer.register_event_handler('klippy:connect', self._handle_connect)
        printer.register_event_handler('flowloop:profile_activated',
                                       self._handle_profile)
        self.gcode = printer.lookup_object('gcode')
        self.tools = self.host.tool_moves('autotemp')
        self.first = self.tools.add(config, self.extruder_name, self)
        if self.first:
            # one command for every tool: the printing one's, or EXTRUDER=
            self.gcode.register_command('AUTOTEMP_FLOW', self.cmd_AUTOTEMP_FLOW,
                                        desc=self.cmd_AUTOTEMP_FLOW_help)
            self.gcode.register_command('SET_AUTOTEMP', self.cmd_SET_AUTOTEMP,
                                        desc=self.cmd_SET_AUTOTEMP_help)
            self.gcode.register_command('QUERY_AUTOTEMP',
                                        self.cmd_QUERY_AUTOTEMP,
                                        desc=self.cmd_QUERY_AUTOTEMP_help)
        self.prev_m104 = self.prev_m109 = None

    # --- setup ---------------------------------------------------------------
    def _handle_connect(self):
        self.extruder = extruder = extruder_for(self.printer, self.section,
                                                self.extruder_name)
        self.heater = extruder.get_heater()
        self.core.set_heater(self.heater.min_temp, self.heater.max_temp)
        self.toolhead = self.printer.lookup_object('toolhead')
        # batch mode: no reading arrives (the heater reads 0 C)
        mcu = self.printer.lookup_object('mcu')
        self.reads_nozzle = heater_reads(
            mcu.is_fileoutput(),
            mcu.estimated_print_time(self.printer.get_reactor().monotonic()))
        # the read-ahead the annotations' LEAD allows for is this host's
        self.core.set_host(flowloop_host.host_facts(self.printer, self.heater,
                                                    self.control_option))
        if self.first:
            # The extruder registers M104 after the extras load: take it over
            # here, as gcode_macro's rename_existing does; one section for
            # all the tools (M104 T1 is extruder1's).
            self.prev_m104 = self.gcode.register_command('M104', None)
            self.gcode.register_command('M104', self.cmd_M104,
                                        desc=self.cmd_M104_help)
            self.prev_m109 = self.gcode.register_command('M109', None)
            self.gcode.register_command('M109', self.cmd_M109,
                                        desc=self.cmd_M109_help)
            self.printer.register_event_handler('extruder:activate_extruder',
                                                self._handle_tool_change)
        self.core.set_working_point(self.working_point)
        active = self.host.get_active_profile(self.extruder_name)
        if active is not None:
            self.core.set_profile(active.profile, active.working_point)
        motion_queuing = self.printer.lookup_object('motion_queuing', None)
        if motion_queuing is not None:
            motion_queuing.register_flush_callback(self._flush)
        else:
            # Kalico: the toolhead's step generators see each flush time
            self.toolhead.register_step_generator(
                lambda flush_time: self._flush(flush_time, flush_time))
        self.tools.join(self)

    def _handle_profile(self, extruder, profile, working_point):
        if extruder == self.extruder_name:
            self.core.set_profile(profile, working_point, self._print_time())

    def _print_time(self):
        # Where queued motion ends, or the MCU's present once it has run
        # past that (an idle toolhead): the core's motion_start_s. Read
        # with check_busy, not the toolhead's whole status: this runs for
        # every extruding move of a file without annotations. Moves still
        # in the lookahead queue come later, so windows placed from here
        # are placed early, never late.
        if self.toolhead is None:
            return 0.
        queued_end, mcu_now, _ = self.toolhead.check_busy(
            self.printer.get_reactor().monotonic())
        return fl_autotemp.motion_start_s(queued_end, mcu_now)

    # --- targets, as the motion is generated ---------------------------------
    def _flush(self, flush_time, step_gen_time):
        # the decision (hold, stand-down, limits, where the model starts) is
        # the core's on_flush
        heater = self.heater.get_status(None)
        target = self.core.on_flush(
            step_gen_time, heater['target'],
            printing=self.toolhead.get_extruder() is self.extruder,
            nozzle_c=heater['temperature'] if self.reads_nozzle else None)
        if target is not None:
            self.heater.set_temp(target)

    # --- tool changes ---------------------------------------------------------
    def _handle_tool_change(self):
        # ACTIVATE_EXTRUDER flushed the old tool's motion first: every other
        # tool stands down and gets its user's target back (never higher).
        printing = self.tools.printing()
        for member in self.tools.members():
            if member is not printing:
                member.stand_down()

    def stand_down(self):
        self.core.stop()
        current = self.heater.get_status(None)['target']
        target = fl_tools.hand_back_target(self.user_target_c, current)
        if target is not None:
            self.heater.set_temp(target)

    # --- the move transform: the lookahead fallback ---------------------------
    def move(self, newpos, speed):
        if self.core.source != 'annotation' and self.core.active:
            shape = fl_caps.move_shape(self.next_transform.get_position(),
                                       newpos)
            if shape.extrudes:   # ToolMoves hands this tool's moves only
                flow = shape.flow_mm3_s(speed, self.extruder.filament_area)
                self.core.on_move(self._print_time(), flow,
                                  shape.duration_s(speed))
        self.next_transform.move(newpos, speed)

    # --- status and commands -------------------------------------------------
    def get_status(self, eventtime=None):
        return self.core.status

    cmd_AUTOTEMP_FLOW_help = (
        "Announce the peak flow (mm^3/s) of a window LEAD s ahead, DURATION s"
        " long (written by flowloop annotate)")

    def cmd_AUTOTEMP_FLOW(self, gcmd):
        # read on every printer, so a bad line is refused with or without
        # a tool to plan for
        low, high = fl_autotemp.ANNOUNCED_FLOW_MM3_S
        flow = number(gcmd, 'FLOW', minimum=low, maximum=high)
        low, high = fl_autotemp.ANNOUNCED_LEAD_S
        lead = number(gcmd, 'LEAD', minimum=low, maximum=high)
        duration = number(gcmd, 'DURATION', above=0.,
                          maximum=fl_autotemp.MAX_ANNOUNCED_DURATION_S)
        # the file's flow is the printing tool's (none: nothing to plan)
        member = self.tools.printing()
        if member is not None:
            member.announce(gcmd, flow, lead, duration)

    def announce(self, gcmd, flow, lead, duration):
        try:
            self.core.announce(self._print_time(), flow, lead, duration)
        except FlowloopError as e:
            raise gcmd.error(f"AUTOTEMP_FLOW: {e}; nothing changed") from None

    cmd_SET_AUTOTEMP_help = (
        "Turn autotemp on (ENABLE=1) or off (ENABLE=0), set its working point"
        " (WP=0..1, or WP=profile for the active profile's)")

    def cmd_SET_AUTOTEMP(self, gcmd):
        self._tool(gcmd).set_autotemp(gcmd)

    def _tool(self, gcmd):
        return self.tools.pick(gcmd.get('EXTRUDER', None), gcmd)

    def set_autotemp(self, gcmd):
        enable = integer(gcmd, 'ENABLE', None, minimum=0, maximum=1)
        wp = gcmd.get('WP', None)
        given = wp is not None
        if given:
            wp = None if wp.strip().lower() == 'profile' \
                else number(gcmd, 'WP', minimum=0., maximum=1.)
            self.working_point = wp
            self.core.set_working_point(wp, self._print_time())
        if enable is not None:
            self.core.set_enabled(bool(enable))
        self.report(gcmd)

    cmd_QUERY_AUTOTEMP_help = "Report autotemp's state, source and target"

    def cmd_QUERY_AUTOTEMP(self, gcmd):
        self._tool(gcmd).report(gcmd)

    cmd_M104_help = ("Set the extruder temperature (ignored while autotemp"
                     " plans the print)")

    def cmd_M104(self, gcmd):
        member, temp_c = self._m104_member(gcmd)
        if member is not None and member.m104(gcmd, temp_c) == 'override':
            return
        self.prev_m104(gcmd)

    cmd_M109_help = "Set the extruder temperature and wait for it"

    def cmd_M109(self, gcmd):
        # always waits (the start G-code's M109 heats as before); the target
        # is kept as the user's for that tool
        member, temp_c = self._m104_member(gcmd)
        if member is not None:
            member.user_target_c = temp_c
            if fl_tools.heater_off(temp_c):
                member.core.stop()
        self.prev_m109(gcmd)

    def _m104_member(self, gcmd):
        """The autotemp of the tool an M104/M109 sets (None: that tool has
        none, or is not configured: Klipper's own M104 answers), its S
        (finite: Klipper's own M104 would set a nan target; its range is
        the heater's, which Klipper's M104 checks)."""
        tool = integer(gcmd, 'T', None, minimum=0)
        temp_c = number(gcmd, 'S', 0., minimum=0.)
        name = fl_tools.m104_extruder(tool, self.tools.active_name())
        member = self.tools.table.get(name)
        if member is not None and member.heater is not None:
            member.check_target(gcmd, temp_c)
        return member, temp_c

    def check_target(self, gcmd, temp_c):
        try:
            fl_tools.check_heater_target(temp_c, self.heater.min_temp,
                                         self.heater.max_temp)
        except FlowloopError as e:
            raise gcmd.error(f"{gcmd.get_command()}: {e}; nothing changed") \
                from None

    def m104(self, gcmd, temp_c):
        action = fl_tools.m104_action(
            temp_c, self.toolhead.get_extruder() is self.extruder,
            self.override_m104 and self.core.overrides_m104())
        self.user_target_c = temp_c
        if action == 'stop':
            self.core.stop()   # turning the heater off is always obeyed
        elif action == 'override':
            gcmd.respond_info(
                f"{self.section}: M104 S{temp_c:g} overridden"
                " (SET_AUTOTEMP ENABLE=0 hands the heater back)")
        return action

    def report(self, gcmd):
        s = self.core.status
        state = "enabled" if s['enabled'] else "disabled"
        target = "none" if s['target'] is None else f"{s['target']:.1f} C"
        flow = "none" if s['planned_flow'] is None \
            else f"{s['planned_flow']:.1f} mm^3/s"
        gcmd.respond_info(
            f"{self.section}: {state}, source {s['source'] or 'none'}, target"
            f" {target}, planned flow {flow}, profile {s['profile'] or 'none'}"
            f" at working point {s['working_point']}"
            + (f"; {s['why']}" if s['why'] else ""))


number = flowloop_host.gcode_number
integer = flowloop_host.gcode_integer


def load_config(config):
    return Autotemp(config)


def load_config_prefix(config):
    return Autotemp(config)
