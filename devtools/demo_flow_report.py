"""Demo step: a flow report of a short print, stored where Moonraker serves it.

With Klipper: the demo printer prints rising flows at 200 C, then at 250 C;
after each move the klippy objects Moonraker's component samples (print
stats, the extruder, the flow sensor twin, the limiter, autotemp) are read
and fed to the same recorder (flowloop.report), at the move's own print
time. Offline: the sensor twin, decoder and grip estimator run in-process.
Either way the report is stored in Moonraker's data path under a demo job
id (not a job of its history: batch-mode klippy runs no print), so
/server/flowloop/reports lists it and /server/flowloop/report serves it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from flowloop.report import dump, render
from flowloop.report.recorder import (
    Job,
    Recorder,
    Sample,
    one_tool,
    sample_from_status,
    status_objects,
)
from flowloop.sensor import ems22
from flowloop.sensor.grip import GripEstimator
from flowloop.sensor.twin import DEFAULT_MELT_LINE, SimulatedEms22

SENSOR = "sim"
AREA = 2.405  # 1.75 mm filament
JOB_ID = "0DE300"   # a demo's, in the form of Moonraker's job ids
# (temperature C, volumetric flow mm^3/s): what the twin melts at 200 C is 10
STEPS = [(200, flow) for flow in (4, 6, 8, 10, 12, 14)] + \
        [(250, flow) for flow in (12, 14)]
MOVE_S = 3.0   # each flow runs this long


def _store(ctx, rec: Recorder) -> None:
    if ctx.printer is None:
        ctx.say("  no Moonraker: the report is not stored")
        return
    folder = Path(ctx.printer.data_dir) / "flowloop" / "reports"
    folder.mkdir(parents=True, exist_ok=True)
    dump.save(folder / f"{JOB_ID}.json", dump.dumps(rec))
    dump.save(folder / f"{JOB_ID}.html", render.html(rec))
    summary = dump.summary(rec)
    ctx.say(f"  {summary['duration_s']:.0f} s recorded: under-extruded"
            f" {summary['under_extruded_mm']} mm; the report lacks:"
            f" {'; '.join(summary['lacks']) or 'nothing'}")
    ctx.say(f"  report: {ctx.moonraker.url}/server/flowloop/report?job_id={JOB_ID}"
            f"  (listed by /server/flowloop/reports)")


def with_klippy(ctx) -> Recorder:
    """Batch-mode klippy runs each move at once, so a sample read after it
    would find the extruder stopped: each move's sample carries its own
    commanded flow and the grip the sensor judged over it, at its start."""
    rec = Recorder(job=Job(job_id=JOB_ID, filename="demo: rising flow",
                           sensor_name=SENSOR))
    tools = one_tool(SENSOR)
    objects = list(status_objects(tools))
    ctx.gcode("G28\nM83\nG1 X20 Y20 Z0.2 F6000\nM400")
    t = 0.0
    for temp_c, flow in STEPS:
        length = flow * MOVE_S / AREA
        speed = length / MOVE_S * 60.0
        ctx.gcode(f"SET_HEATER_TEMPERATURE HEATER=extruder TARGET={temp_c}\n"
                  f"G1 E{length:.3f} F{speed:.1f}\nM400")
        sample = sample_from_status(t, ctx.query_many(*objects), tools)
        grip = sample.grip if sample.grip is not None else 1.0
        rec.sample(dataclasses.replace(sample, commanded_flow_mm3_s=float(flow),
                                       measured_flow_mm3_s=flow * grip))
        t += MOVE_S
    ctx.gcode("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=0")
    rec.sample(Sample(time_s=t, commanded_flow_mm3_s=0.0))
    rec.finish("completed", t)
    return rec


def offline() -> Recorder:
    rec = Recorder(job=Job(job_id=JOB_ID, filename="demo: rising flow (offline)",
                           sensor_name=SENSOR))
    t = 0.0
    for temp_c, flow in STEPS:
        sim = SimulatedEms22(DEFAULT_MELT_LINE, seed=1)
        decoder = ems22.Decoder(bit_offset=sim.bit_offset)
        times = np.arange(0, MOVE_S, ems22.DEFAULT_SAMPLE_PERIOD_S)
        commanded = (flow / AREA) * times
        samples = decoder.decode(sim.messages(times, commanded, temp_c))
        est = GripEstimator()
        est.add(times, samples.counts / sim.counts_per_mm, commanded)
        measured, _ = est.flows()
        rec.sample(Sample(time_s=t, commanded_flow_mm3_s=float(flow),
                          measured_flow_mm3_s=measured, grip=est.grip,
                          temp_c=float(temp_c), target_c=float(temp_c)))
        t += MOVE_S
    rec.sample(Sample(time_s=t, commanded_flow_mm3_s=0.0))
    rec.finish("completed", t)
    return rec


def demo(ctx) -> None:
    ctx.say("A flow report of the demo print (flows rising past what the twin"
            " melts at 200 C, then at 250 C), as Moonraker records a job:")
    rec = with_klippy(ctx) if ctx.klippy_available else offline()
    _store(ctx, rec)
