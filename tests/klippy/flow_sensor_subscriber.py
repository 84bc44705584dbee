"""klippy with a test subscriber on every [flow_sensor]: run in place of
klippy.py (cwd: the Klipper tree), it logs each grip window the sensor
delivers through subscribe_grip_windows, as another flowloop section would
receive it, with the thread it arrived on."""

import dataclasses
import json
import logging
import os
import runpy
import sys
import threading

KLIPPY = os.path.join(os.getcwd(), "klippy", "klippy.py")
sys.path.insert(0, os.path.dirname(KLIPPY))
sys.argv[0] = KLIPPY

import extras.flow_sensor as flow_sensor  # noqa: E402

load_config_prefix = flow_sensor.load_config_prefix


def load_and_subscribe(config):
    sensor = load_config_prefix(config)

    def record(window):
        fields = dataclasses.asdict(window)
        fields["sensor"] = sensor.name
        fields["reactor_thread"] = (threading.current_thread()
                                    is threading.main_thread())
        logging.info("GRIP_WINDOW %s", json.dumps(fields))

    sensor.subscribe_grip_windows(record)
    return sensor


flow_sensor.load_config_prefix = load_and_subscribe
runpy.run_path(KLIPPY, run_name="__main__")
