"""Demo step: the simulated EMS22 flow sensor follows a short print.

With Klipper: the demo printer's [flow_sensor_simulation sim] twin
(config/printer.cfg) follows extrude moves and printed lines at rising
volumetric flow; grip drops once the flow exceeds what its hotend melts at
200 C and recovers at 250 C. Offline: the same twin, decoder and grip
estimator run in-process.
"""

from __future__ import annotations

import numpy as np

from flowloop.sensor import ems22
from flowloop.sensor.grip import GripEstimator
from flowloop.sensor.twin import DEFAULT_MELT_LINE, SimulatedEms22

SENSOR = "flow_sensor sim"
AREA = 2.405  # 1.75 mm filament
# (what, temperature C, E mm, G-code) -- lines are 0.4 x 0.2 mm = 0.08 mm^2:
# 130 mm of line uses 130 * 0.08 / 2.405 = 4.32 mm of filament
PRINT = [
    ("extrude 5 mm^3/s", 200, 15, "G1 E15 F125"),
    ("line 8 mm^3/s", 200, 4.32, "G1 X150 Y20 E4.32 F6000"),
    ("line 16 mm^3/s", 200, 4.32, "G1 X20 Y20 E4.32 F12000"),
    ("extrude 20 mm^3/s", 200, 30, "G1 E30 F499"),
    ("extrude 20 mm^3/s", 250, 30, "G1 E30 F499"),
]


def _grip(grip) -> str:
    return "not judged" if grip is None else f"{grip:.3f}"


def with_klippy(ctx) -> None:
    ctx.say("The demo printer's simulated sensor (melts 10 mm^3/s at 200 C, "
            "+0.2 per degree) follows a short print:")
    ctx.gcode("G28\nM83\nG1 X20 Y20 Z0.2 F6000\nM400\nQUERY_FLOW_SENSOR SENSOR=sim")
    for what, temp_c, length, move in PRINT:
        before = ctx.query(SENSOR)["filament_position"] or 0.0
        ctx.gcode(f"SET_HEATER_TEMPERATURE HEATER=extruder TARGET={temp_c}\n"
                  f"{move}\nM400\nQUERY_FLOW_SENSOR SENSOR=sim")
        status = ctx.query(SENSOR)
        moved = status["filament_position"] - before
        ctx.say(f"  {what:18s} at {temp_c} C: commanded {length:5.2f} mm, sensor"
                f" saw {moved:5.2f} mm, grip {_grip(status['grip'])}")
    status = ctx.query(SENSOR)
    ctx.say(f"  {status['samples']} samples at {status['sample_rate']:.0f}/s, "
            f"filament position {status['filament_position']} mm, "
            f"errors {status['errors'] or 'none'}, fault {status['fault']}")
    ctx.gcode("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=0")


def offline(ctx) -> None:
    ctx.say("No klippy: the same twin, decoder and grip estimator in-process.")
    for flow, temp_c in ((5, 200), (8, 200), (16, 200), (20, 200), (20, 250)):
        sim = SimulatedEms22(DEFAULT_MELT_LINE, seed=1)
        decoder = ems22.Decoder(bit_offset=sim.bit_offset)
        times = np.arange(0, 3.0, ems22.DEFAULT_SAMPLE_PERIOD_S)
        commanded = (flow / AREA) * times
        samples = decoder.decode(sim.messages(times, commanded, temp_c))
        est = GripEstimator()
        est.add(times, samples.counts / sim.counts_per_mm, commanded)
        measured, commanded_flow = est.flows()
        ctx.say(f"  flow {flow:2d} mm^3/s at {temp_c} C: measured {measured:5.1f}"
                f" mm^3/s, grip {_grip(est.grip)}")


def demo(ctx) -> None:
    if ctx.klippy_available:
        with_klippy(ctx)
    else:
        offline(ctx)
