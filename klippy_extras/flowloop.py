# flowloop's shared klippy object: what is loaded, what the firmware has,
# and the active material profile of each extruder.
#
# Loaded by every flowloop section (printer.load_object(config, 'flowloop')),
# or on its own with a [flowloop] section. Moonraker's flowloop component
# reads it (printer.objects.query flowloop) for /server/flowloop/info and
# sends the active profiles through the flowloop/set_active_profile endpoint.
#
# Every flowloop module imports this one before the core: a core or a
# requirement of it (numpy...) missing from klippy's Python is then one config
# error naming what to install, as Klipper does for numpy, not an internal
# error at the first import of numpy.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import logging
import os
import sys

if (__package__ or '').startswith('klippy.'):   # Kalico: klippy.plugins
    from .. import configfile
else:   # Klipper: klippy/ is on the path
    import configfile

try:    # the core alone first: it imports only the standard library
    from flowloop.host import requirements
except ImportError:
    raise configfile.error(
        f"klippy's Python ({sys.executable}) has no flowloop: run"
        f" {os.path.join(os.path.dirname(sys.executable), 'pip')} install"
        f" klipper-flowloop (or pip install -e on a flowloop checkout)") from None
if requirements.missing() is not None:
    raise configfile.error(requirements.missing())
# isort: split
import flowloop
from flowloop.control import nozzle_health as fl_nozzle_health
from flowloop.control.tools import PerTool
from flowloop.errors import FlowloopError
from flowloop.host import klipper_config
from flowloop.material import profile as fl_profile
from flowloop.material.active import Activation, working_point_arg
from flowloop.numbers import REQUIRED, read_integer, read_number
from flowloop.sensor import ems22

SECTIONS = ('flow_sensor', 'flow_sensor_simulation', 'flowrate_limiter',
            'autotemp', 'diff_ab_calibrate', 'endstop_calibrate')


class FlowloopHost:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.sensor_firmware = {}
        self.sections = ()  # flowloop sections loaded: known once connected
        # extruder name -> Activation; status is rebuilt on change
        self.active_profiles = {}
        self.status = self._status({})
        self.tools = {}   # kind -> ToolMoves: the per-tool sections of a kind
        self.printer.register_event_handler('klippy:connect',
                                            self._handle_connect)
        webhooks = self.printer.lookup_object('webhooks')
        webhooks.register_endpoint('flowloop/set_active_profile',
                                   self._handle_set_active_profile)

    def stage_for_save_config(self, items):
        """Stage (section, option, value) items for SAVE_CONFIG.

        Values that an included file sets cannot be saved (SAVE_CONFIG would
        refuse them all): those are left out. Returns (staged items, lines
        telling the user what to paste where).
        """
        config_file = self.printer.get_start_args().get('config_file')
        try:
            stageable, paste = klipper_config.save_plan(config_file, items)
        except (FlowloopError, OSError) as e:
            logging.warning("flowloop: cannot read %s (%s); staging all",
                            config_file, e)
            stageable, paste = list(items), []
        configfile = self.printer.lookup_object('configfile')
        for section, option, value in stageable:
            configfile.set(section, option, value)
        return stageable, paste

    def _handle_connect(self):
        loaded = [(name, obj) for name, obj in self.printer.lookup_objects()
                  if name.split()[0] in SECTIONS]
        # a simulation is also registered as [flow_sensor NAME]: listed once,
        # by the section the config has
        simulated = {id(obj) for name, obj in loaded
                     if name.split()[0] == 'flow_sensor_simulation'}
        self.sections = tuple(sorted(
            name for name, obj in loaded
            if name.split()[0] != 'flow_sensor' or id(obj) not in simulated))
        for name, mcu in self.printer.lookup_objects('mcu'):
            self.sensor_firmware[name] = _has_command(mcu, ems22.QUERY_CMD)
        self.status = self._status(self.status['profiles'])

    def _handle_set_active_profile(self, web_request):
        extruder = web_request.get_str('extruder', 'extruder')
        heater = self._extruder_heater(extruder)
        if heater is None:
            raise web_request.error(f"flowloop: no extruder named {extruder!r}")
        data = web_request.get('profile', None)
        if data is None:
            self.active_profiles.pop(extruder, None)
            self._update_status()
            self.printer.send_event('flowloop:profile_activated', extruder,
                                    None, None)
            web_request.send({'extruder': extruder, 'name': None})
            return
        try:
            wp = working_point_arg(web_request.get(
                'working_point', fl_profile.DEFAULT_WORKING_POINT))
            # the hotend's melt ratio from its earlier prints (Moonraker's
            # nozzle health): the limiter's grip model starts from it
            ratio = web_request.get('melt_ratio', None)
            ratio = None if ratio is None else fl_nozzle_health.melt_ratio_arg(ratio)
            # Whatever the profile says, never above the heater's limit.
            profile = fl_profile.capped_to_heater(
                fl_profile.profile_from_dict(data), heater.max_temp)
        except FlowloopError as e:
            raise web_request.error(f"flowloop: {e}") from None
        self.active_profiles[extruder] = Activation(profile, wp, ratio)
        self._update_status()
        self.printer.send_event('flowloop:profile_activated', extruder,
                                profile, wp)
        web_request.send({'extruder': extruder, 'name': profile.name})

    def _extruder_heater(self, name):
        if not fl_profile.is_extruder_name(name):
            return None
        extruder = klipper_config.find_extruder(self.printer, name)
        return None if extruder is None else extruder.get_heater()

    def _update_status(self):
        status = {}
        for extruder, active in sorted(self.active_profiles.items()):
            entry = fl_profile.active_status(active.profile,  # capped bounds
                                             active.working_point)
            entry['heater_max_temp_c'] = self._extruder_heater(extruder).max_temp
            status[extruder] = entry
        self.status = self._status(status)

    def _status(self, profiles):
        # Built when something changes: get_status only hands it out.
        return {'version': flowloop.__version__,
                'sections': self.sections,
                'sensor_firmware': dict(self.sensor_firmware),
                'profiles': profiles}

    def tool_moves(self, kind):
        """The one ToolMoves of a kind ('flowrate_limiter', 'autotemp')."""
        if kind not in self.tools:
            self.tools[kind] = ToolMoves(self.printer, kind)
        return self.tools[kind]

    def get_active_profile(self, extruder='extruder'):
        """The Activation (profile, working_point) of an extruder, or None."""
        return self.active_profiles.get(extruder)

    def get_status(self, eventtime=None):
        return self.status


def named_tool(config, kind):
    """The extruder a per-tool section's name says ([flowrate_limiter
    extruder1] -> extruder1), or None for the plain section, which reads its
    `extruder` option itself (a named section refuses that option, as
    Klipper does any option it does not read)."""
    section = config.get_name()
    return klipper_config.section_extruder(section) if section != kind else None


class ToolMoves:
    """One move transform for all the sections of a kind, one section per
    extruder: each G-code move goes to the section of the extruder that
    prints (the toolhead's, which ACTIVATE_EXTRUDER and T0/T1 macros change),
    so a move is handled once however many tools there are. Registered at
    klippy:connect by the first section to join, chaining the transform it
    replaces (as skew_correction.py)."""

    def __init__(self, printer, kind):
        self.printer = printer
        self.table = PerTool(kind)
        self.next_transform = self.toolhead = None

    def add(self, config, extruder_name, member):
        """At config time: refuse a second section for one extruder. True
        for the first section, which registers the kind's commands (they go
        to the section pick() names)."""
        try:
            self.table.add(config.get_name(), extruder_name, member)
        except FlowloopError as e:
            raise config.error(str(e)) from None
        return len(self.table.extruders) == 1

    def join(self, member):
        """At klippy:connect, once the section found its extruder."""
        if self.next_transform is None:
            self.toolhead = self.printer.lookup_object('toolhead')
            gcode_move = self.printer.lookup_object('gcode_move')
            self.next_transform = gcode_move.set_move_transform(self,
                                                                force=True)
        member.next_transform = self.next_transform

    def printing(self):
        """The section of the extruder that prints, or None."""
        return self.table.get(self.active_name())

    def members(self):
        """Every section of the kind, one per extruder."""
        return self.table.members()

    def active_name(self):
        return self.toolhead.get_extruder().get_name()

    def pick(self, extruder_name, gcmd):
        """The section of the extruder a command names (its EXTRUDER=),
        else the printing one's."""
        try:
            return self.table.pick(extruder_name, self.active_name())
        except FlowloopError as e:
            raise gcmd.error(f"{gcmd.get_command()}: {e}") from None

    def get_position(self):
        return self.next_transform.get_position()

    def move(self, newpos, speed):
        member = self.printing()
        if member is None:
            self.next_transform.move(newpos, speed)
        else:
            member.move(newpos, speed)


def gcode_number(gcmd, name, default=REQUIRED, **bounds):
    """A number parameter of a flowloop command, read by flowloop's one
    reader (Klipper's get_float lets nan through its range checks, reads
    1_000 and other scripts' digits); bounds: above=, minimum=, maximum=.
    A refusal is one line naming the command, the parameter and the bound."""
    return _read(gcmd, read_number, name, default, bounds)


def gcode_integer(gcmd, name, default=REQUIRED, **bounds):
    """A whole-number parameter (ENABLE=1, LAYER=3): minimum=, maximum=."""
    return _read(gcmd, read_integer, name, default, bounds)


def _read(gcmd, reader, name, default, bounds):
    try:
        return reader(gcmd.get(name, None), name, default, **bounds)
    except FlowloopError as e:
        raise gcmd.error(f"{gcmd.get_command()}: {e}; nothing changed") \
            from None


def heater_control_option(config, extruder_name):
    """The heater control the extruder's section names (`control: pid`),
    read at config time as the user wrote it; None if it names none."""
    return config.getsection(extruder_name).get('control', None)


def host_facts(printer, heater, control_option):
    """What this klippy offers that flowloop's timing and heating depend on
    (flowloop.host.klipper_config.host_facts), read once at connect: Kalico
    always loads its [danger_options] object and names its heater's control
    itself; on Klipper the control is the one the config names."""
    kalico = printer.lookup_object('danger_options', None) is not None
    control = heater.get_control().get_type() if kalico else control_option
    return klipper_config.host_facts(kalico, control)


def _has_command(mcu, msgformat):
    """Whether the MCU's firmware has a command (Kalico's MCU has no
    check_valid_response; try_lookup_command is in both hosts)."""
    check = getattr(mcu, 'check_valid_response', None)
    if check is not None:
        return check(msgformat)
    return mcu.try_lookup_command(msgformat) is not None


def load_config(config):
    return FlowloopHost(config)
