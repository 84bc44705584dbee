"""klippy as test_measure_profile.py needs it: run in place of klippy.py (cwd:
the Klipper tree). Every [flow_sensor_simulation NAME] gets an API endpoint
measure_profile_test/fault/NAME (fault=missing|magnet|parity|none) that makes
its twin misbehave at once, between two G-code commands (a running
MEASURE_MATERIAL_PROFILE takes the G-code queue step by step).
flowloop itself ships no such endpoint."""

import os
import runpy
import sys

KLIPPY = os.path.join(os.getcwd(), "klippy", "klippy.py")
sys.path.insert(0, os.path.dirname(KLIPPY))
sys.argv[0] = KLIPPY

if os.path.isdir(os.path.join(os.path.dirname(KLIPPY), "plugins")):
    # Kalico loads flowloop's modules as the package klippy.plugins
    sys.path.insert(0, os.path.dirname(os.path.dirname(KLIPPY)))
    import klippy.plugins.flow_sensor_simulation as simulation  # noqa: E402
else:
    import extras.flow_sensor_simulation as simulation  # noqa: E402

load_config_prefix = simulation.load_config_prefix


def load_for_tests(config):
    sensor = load_config_prefix(config)

    def fault(web_request):
        name = web_request.get_str("fault")
        sensor.source.catch_up()
        sensor.source.twin.set_fault(None if name == "none" else name)
        web_request.send({"fault": name})

    webhooks = config.get_printer().lookup_object("webhooks")
    webhooks.register_endpoint(f"measure_profile_test/fault/{sensor.name}",
                               fault)
    return sensor


simulation.load_config_prefix = load_for_tests
runpy.run_path(KLIPPY, run_name="__main__")
