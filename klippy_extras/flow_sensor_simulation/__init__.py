# [flow_sensor_simulation NAME]: the simulated flow sensor of demos and tests
# (the demo printer, the klippy test tier): a host-side twin of the EMS22 on
# the extruder's real steps, with no pins and no MCU command, whose hotend
# model may stand in for the heater's thermistor. To every other section,
# command and client it is the flow sensor [flow_sensor NAME].
#
# A real printer has no such section, so klippy never imports the twin:
# Klipper imports a module for the sections a config has, Kalico imports
# every plugin at start, hence the twin is imported here, when the section
# is loaded.
#
# This file may be distributed under the terms of the GNU GPLv3 license.


def load_config_prefix(config):
    from .twin import load_simulated_sensor
    return load_simulated_sensor(config)
