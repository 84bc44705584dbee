"""klippy as the flow_sensor tests need it: run in place of klippy.py (cwd:
the Klipper tree) for the runs test_flow_sensor.py makes with `Harnessed`.

- Every flow sensor ([flow_sensor], [flow_sensor_simulation]) gets a
  subscriber that logs each grip window it delivers through
  subscribe_grip_windows ("GRIP_WINDOW {json}"), as another flowloop section
  would receive it, with the thread it arrived on.
- Every ems22 sensor gets FLOW_SENSOR_FEED SENSOR= SEQUENCE= DATA=(hex)
  [SYNC=1]: the payload goes to the callback the sensor registered with the
  MCU's serial reader for sensor_bulk_data (what the serial thread calls),
  then (SYNC=1) the sensor processes its queue, as its reactor timer would.
  In batch mode the MCU never answers, so this is how real-format messages
  reach the real path. flowloop itself ships no such command: a printer
  never needs it.
- With FLOW_SENSOR_PROFILE=1 in the environment, the CPU time spent in each
  sensor's process() (decode, timing, commanded positions, grip) is summed
  and printed at exit: "PROCESS_CPU name seconds samples calls".
- When klippy is ready the log says which modules named *twin it imported
  ("TWIN_MODULES ..." or "TWIN_MODULES none").
"""

import atexit
import dataclasses
import json
import logging
import os
import runpy
import sys
import threading
import time

KLIPPY = os.path.join(os.getcwd(), "klippy", "klippy.py")
sys.argv[0] = KLIPPY
if os.path.isfile(os.path.join(os.getcwd(), "klippy", "plugins", "__init__.py")):
    # Kalico: klippy is a package, flowloop's modules are its plugins
    sys.path.insert(0, os.getcwd())
    import klippy.extras.bulk_sensor as bulk_sensor  # noqa: E402
    import klippy.plugins.flow_sensor as flow_sensor  # noqa: E402
    import klippy.plugins.flow_sensor_simulation as simulation  # noqa: E402
else:
    sys.path.insert(0, os.path.dirname(KLIPPY))
    import extras.bulk_sensor as bulk_sensor  # noqa: E402
    import extras.flow_sensor as flow_sensor  # noqa: E402
    import extras.flow_sensor_simulation as simulation  # noqa: E402

LOADERS = {flow_sensor: flow_sensor.load_config_prefix,
           simulation: simulation.load_config_prefix}


def subscribe(sensor):
    def record(window):
        fields = dataclasses.asdict(window)
        fields["sensor"] = sensor.name
        fields["reactor_thread"] = (threading.current_thread()
                                    is threading.main_thread())
        logging.info("GRIP_WINDOW %s", json.dumps(fields))

    sensor.subscribe_grip_windows(record)


def add_feed(config, sensor):
    source = sensor.source

    def feed(gcmd):
        payload = bytes.fromhex(gcmd.get("DATA"))
        if len(payload) > bulk_sensor.MAX_BULK_MSG_SIZE:
            raise gcmd.error("DATA is longer than a sensor_bulk_data message")
        handler = source.mcu._serial.handlers["sensor_bulk_data", source.oid]
        # the params msgproto hands the handler (%*s parsed to bytes)
        handler({"#name": "sensor_bulk_data", "oid": source.oid,
                 "sequence": gcmd.get_int("SEQUENCE", minval=0, maxval=0xffff),
                 "data": payload})
        if gcmd.get_int("SYNC", 1):
            source.sync()

    gcode = config.get_printer().lookup_object("gcode")
    gcode.register_mux_command("FLOW_SENSOR_FEED", "SENSOR", sensor.name, feed,
                               desc="test harness: feed a sensor_bulk_data payload")


def profile(sensor):
    totals = {"cpu": 0.0, "samples": 0, "calls": 0}
    process = sensor.process

    def timed(messages):
        samples = sensor.pipeline.rate.total
        start = time.process_time()
        process(messages)
        totals["cpu"] += time.process_time() - start
        totals["samples"] += sensor.pipeline.rate.total - samples
        totals["calls"] += 1

    sensor.process = timed
    atexit.register(lambda: sys.stderr.write(
        f"PROCESS_CPU {sensor.name} {totals['cpu']:.6f} {totals['samples']}"
        f" {totals['calls']}\n"))


def loaded_for_tests(load_config_prefix):
    def load_for_tests(config):
        sensor = load_config_prefix(config)
        if os.environ.get("FLOW_SENSOR_PROFILE"):
            profile(sensor)    # no logging subscriber in the measured time
        else:
            subscribe(sensor)
        if isinstance(sensor.source, flow_sensor.Ems22Source):
            add_feed(config, sensor)
        config.get_printer().register_event_handler("klippy:ready",
                                                    log_twin_imported)
        return sensor
    return load_for_tests


def log_twin_imported():
    # Once every section is loaded: a printer without
    # [flow_sensor_simulation] never imports the twin
    twins = sorted(name for name in sys.modules if name.endswith("twin"))
    logging.info("TWIN_MODULES %s", " ".join(twins) or "none")


for module, load in LOADERS.items():
    module.load_config_prefix = loaded_for_tests(load)
runpy.run_path(KLIPPY, run_name="__main__")
