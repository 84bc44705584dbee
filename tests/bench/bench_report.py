"""The flow report's cost over a long print, against the print itself.

The print is the 25 MB file of the annotate bench (bench_annotate.large_file:
the shared data's parts.gcode four times over when FLOWLOOP_BENCH_GCODE has
it, else the shipped excerpt's layers again and again), planned by
flowloop.gcode.bulk_planner for its commanded flow over time and its layers. The
recorder is fed what the Moonraker component feeds it: one Sample every
SAMPLE_PERIOD_S of print time (the commanded flow, a measured flow at a grip
with the sensor's noise and a slip now and then, temperatures, the layer).

Figures: the recorder's CPU time as a share of the print's duration (what
sampling costs Moonraker's process per second of printing), its memory
(tracemalloc, everything the recorder holds) after the first hour and at the
end (the time bins and spans are bounded; the per-layer table grows by one
small row a layer, so a long print of many layers holds more), the dump's
size, and the time to render the HTML report at the end.
"""

from __future__ import annotations

import time
import tracemalloc

import numpy as np

from flowloop.gcode.bulk_planner import Segments, plan_batches
from flowloop.report import dump, render
from flowloop.report.recorder import SAMPLE_PERIOD_S, Job, Recorder, Sample
from tests.bench.bench_annotate import large_file

AREA_MM2 = 2.405
HOUR_S = 3600.0


def _print_plan(path):
    """(sample times, commanded flow at each, layer at each) of the file."""
    starts, flows, offsets = [], [], []
    with open(path, "rb") as f:
        for batch in plan_batches(f):
            if isinstance(batch, Segments):
                starts.append(batch.start_s)
                flows.append(batch.flow_mm3_s)
                offsets.append(batch.offset)
    starts, flows = np.concatenate(starts), np.concatenate(flows)
    offsets = np.concatenate(offsets)
    data = path.read_bytes()
    layer_offsets, at = [], data.find(b";LAYER_CHANGE")
    while at >= 0:
        layer_offsets.append(at)
        at = data.find(b";LAYER_CHANGE", at + 1)
    end = float(starts[-1])
    times = np.arange(0.0, end, SAMPLE_PERIOD_S)
    index = np.searchsorted(starts, times, side="right") - 1
    layers = np.searchsorted(layer_offsets, offsets[index], side="right")
    return times, flows[index], layers


def _feed(times, flows, layers, rng, until_s=None):
    rec = Recorder(job=Job(job_id="00002A", filename="large.gcode",
                           sensor_name="filament"))
    grips = 1.0 + rng.normal(0.0, 0.005, len(times))
    slipping = (np.arange(len(times)) // 2400) % 50 == 7   # 10 min in ~8 h
    grips[slipping] *= 0.85
    for t, flow, grip, layer in zip(times.tolist(), flows.tolist(),
                                    grips.tolist(), layers.tolist()):
        if until_s is not None and t > until_s:
            break
        rec.sample(Sample(time_s=t, commanded_flow_mm3_s=flow,
                          measured_flow_mm3_s=flow * grip, grip=grip,
                          temp_c=215.0, target_c=215.0, planned_temp_c=215.0,
                          cap_mm3_s=None, layer=int(layer) + 1,
                          profile="PLA", working_point=0.5))
    return rec


def _held_bytes(times, flows, layers, until_s):
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    rec = _feed(times, flows, layers, np.random.default_rng(1), until_s)
    held = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    return held, rec


def test_report_cost_over_a_long_print(tmp_path, bench):
    src = large_file(tmp_path)
    times, flows, layers = _print_plan(src)
    duration = float(times[-1])
    bench.figure("report bench print: duration", duration / HOUR_S, " h")
    bench.figure("report bench print: samples", len(times))
    bench.figure("report bench print: layers", int(layers[-1]) + 1)

    start = time.process_time()
    rec = _feed(times, flows, layers, np.random.default_rng(1))
    cpu = time.process_time() - start
    bench.figure("report recorder CPU time as a share of the print's duration",
                 cpu / duration * 100, " %", goal="<= 0.1 %")
    bench.figure("report recorder CPU per hour of print", cpu / duration
                 * HOUR_S * 1000, " ms")

    first_hour, early = _held_bytes(times, flows, layers, HOUR_S)
    whole, _ = _held_bytes(times, flows, layers, None)
    # the bins and spans are bounded; the per-layer table grows by a layer
    bench.ratio("report memory held after the whole print vs after its first"
                " hour", whole / 1024, first_hour / 1024, " kB",
                goal="bounded but for the per-layer table")
    bench.figure("report memory per layer beyond the first hour's",
                 (whole - first_hour) / max(1, len(rec.layers)
                                            - len(early.layers)), " B")

    rec.finish("completed", duration)
    text = dump.dumps(rec)
    bench.figure("report dump size", len(text) / 1024, " kB")
    start = time.process_time()
    html = render.html(dump.loads(text))
    bench.figure("report render at the end (CPU)", time.process_time() - start,
                 " s")
    bench.figure("report HTML size", len(html) / 1024, " kB")
    assert rec.samples == len(times)
