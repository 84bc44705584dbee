# flowloop's shared klippy object: what is loaded and what the firmware has.
#
# Loaded by every flowloop section (printer.load_object(config, 'flowloop')),
# or on its own with a [flowloop] section. Moonraker's flowloop component
# reads it (printer.objects.query flowloop) for /server/flowloop/info.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import flowloop
from flowloop import ems22

SECTIONS = ('flow_sensor', 'flowrate_limiter', 'autotemp',
            'diff_ab_calibrate', 'endstop_calibrate')


class FlowloopHost:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.sensor_firmware = {}
        self.printer.register_event_handler('klippy:connect',
                                            self._handle_connect)

    def _handle_connect(self):
        for name, mcu in self.printer.lookup_objects('mcu'):
            self.sensor_firmware[name] = mcu.check_valid_response(
                ems22.QUERY_CMD)

    def loaded_sections(self):
        return sorted(name for name, obj in self.printer.lookup_objects()
                      if name.split()[0] in SECTIONS)

    def get_status(self, eventtime=None):
        return {'version': flowloop.__version__,
                'sections': self.loaded_sections(),
                'sensor_firmware': dict(self.sensor_firmware)}


def load_config(config):
    return FlowloopHost(config)
