"""klippy as test_fuzz_gcode.py needs it: run in place of klippy.py (cwd: the
Klipper tree) so that one batch run can send a thousand bad commands.

- A refused command is logged as "FUZZ_REFUSED <message>" and does not end
  the run: in batch mode Klipper ends the reactor at the first error, so the
  rest of a file would never be read. Everything else is Klipper's own
  (an internal error still shuts the printer down and says so).
- FUZZ_STATE N=<i> logs "FUZZ_STATE <i> {json}": what a refused command must
  leave as it was: every stepper's rotation_distance (the extruders' too),
  heater targets, what SAVE_CONFIG would write, the toolhead's position and
  homed axes, whether the printer is shut down, and the settings of each
  flowloop section (limiter, autotemp, sensor calibration, measurement,
  calibration results, active profiles).
flowloop itself ships none of this: a printer never needs it.
"""

import json
import logging
import os
import runpy
import sys

KLIPPY = os.path.join(os.getcwd(), "klippy", "klippy.py")
sys.argv[0] = KLIPPY
if os.path.isfile(os.path.join(os.getcwd(), "klippy", "plugins", "__init__.py")):
    # Kalico: klippy is a package, flowloop's modules are its plugins
    sys.path.insert(0, os.getcwd())
    import klippy.plugins.flowloop as flowloop_module  # noqa: E402
else:
    sys.path.insert(0, os.path.dirname(KLIPPY))
    import extras.flowloop as flowloop_module  # noqa: E402

# flowloop's sections and the status fields a refusal must not change
SECTION_FIELDS = {
    'flowloop': None,    # the whole status: the active profiles
    'flowrate_limiter': ('enabled', 'mode', 'max_flow', 'min_grip', 'profile'),
    'autotemp': ('enabled', 'working_point', 'profile', 'source'),
    'flow_sensor': ('calibration', 'simulation', 'fault'),
    'measure_profile': ('state', 'name'),
    'diff_ab_calibrate': ('rotation_distance', 'iterations', 'last_result'),
    'endstop_calibrate': ('last_result',),
}


def state(printer):
    eventtime = printer.get_reactor().monotonic()
    toolhead = printer.lookup_object('toolhead')
    steppers = list(toolhead.get_kinematics().get_steppers())
    for name, obj in printer.lookup_objects():
        if name.startswith('extruder') and hasattr(obj, 'extruder_stepper'):
            steppers.append(obj.extruder_stepper.stepper)
    heaters = printer.lookup_object('heaters', None)
    targets = {}
    names = [] if heaters is None \
        else heaters.get_status(eventtime)['available_heaters']
    for name in names:
        heater = printer.lookup_object(name)
        targets[name] = heater.get_status(eventtime)['target']
    configfile = printer.lookup_object('configfile').get_status(eventtime)
    th = toolhead.get_status(eventtime)
    sections = {}
    for name, obj in printer.lookup_objects():
        fields = SECTION_FIELDS.get(name.split()[0], ())
        if fields == () or not hasattr(obj, 'get_status'):
            continue
        status = obj.get_status(eventtime)
        sections[name] = (status if fields is None else
                          {f: status.get(f) for f in fields})
    return {
        'shutdown': printer.is_shutdown(),
        'rotation_distance': {s.get_name(): s.get_rotation_distance()[0]
                              for s in steppers},
        'heater_targets': targets,
        'save_config_pending_items': configfile['save_config_pending_items'],
        'position': [round(v, 6) for v in th['position']],
        'homed_axes': th['homed_axes'],
        'sections': sections,
    }


def install(printer):
    gcode = printer.lookup_object('gcode')
    respond_error = gcode._respond_error

    def refused(msg):
        logging.warning("FUZZ_REFUSED %s", msg.strip().split('\n')[0])
        fileinput, gcode.is_fileinput = gcode.is_fileinput, False
        try:
            respond_error(msg)
        finally:
            gcode.is_fileinput = fileinput

    gcode._respond_error = refused

    def fuzz_state(gcmd):
        logging.info("FUZZ_STATE %s %s", gcmd.get('N'),
                     json.dumps(state(printer), sort_keys=True, default=str))

    gcode.register_command('FUZZ_STATE', fuzz_state,
                           desc="test harness: log the printer's state")


load_config = flowloop_module.load_config


def load_for_fuzz(config):
    host = load_config(config)
    install(config.get_printer())
    return host


flowloop_module.load_config = load_for_fuzz
runpy.run_path(KLIPPY, run_name="__main__")
