"""The flow sensor's pipeline, fed by the simulated EMS22 as [flow_sensor]'s
sources feed it: windows, faults by one path, the status policy."""

from __future__ import annotations

import numpy as np
import pytest

from flowloop.errors import FlowloopError
from flowloop.material import procedure as proc
from flowloop.material.profile import Line
from flowloop.sensor import ems22
from flowloop.sensor.pipeline import (
    Motion,
    SampleTiming,
    SensorPipeline,
    Settings,
)
from flowloop.sensor.twin import SimulatedEms22
from flowloop.window import FAULT, JUDGED, Window

pytestmark = pytest.mark.unit

FREQ = 16e6
PERIOD_S = 0.004
SPEED_MM_S = 2.0


class LineMotion(Motion):
    """An extruder feeding SPEED_MM_S from print time 0, planned as one move."""

    def __init__(self, speed=SPEED_MM_S):
        self.speed = speed

    def commanded_at(self, times):
        return self.speed * np.asarray(times)

    def planned_moves(self, start, end):
        return [(0.0, 1e6, self.speed, 0.0, 0.0, 1.0)]

    def temp_c(self):
        return 215.0


def timing():
    return SampleTiming(start_clock=0, rest_ticks=int(PERIOD_S * FREQ),
                        time_shift=0, clock_to_print_time=lambda c: c / FREQ)


def run(pipeline, twin, seconds, start_s=0.0, motion=None):
    """Feed `seconds` of samples from start_s; every Batch it gave."""
    motion = motion or LineMotion()
    batches = []
    n = int(round(seconds / PERIOD_S))
    first = int(round(start_s / PERIOD_S))
    for chunk in range(first, first + n, 25):     # 100 ms batches
        times = np.arange(chunk, min(chunk + 25, first + n)) * PERIOD_S
        messages = twin.messages(times, motion.commanded_at(times), 215.0)
        batches.append(pipeline.feed(messages, timing(), motion))
    return batches


def weak_twin(grip):
    # a melt line that lets through `grip` of the 2 mm/s (4.8 mm^3/s) fed
    flow = grip * SPEED_MM_S * 2.405
    return SimulatedEms22(Line(0.0, flow), noise_counts=0)


def test_windows_carry_the_twins_grip_and_status_reports_it():
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S))
    batches = run(pipeline, weak_twin(0.9), 4.0)
    windows = [w for b in batches for w in b.windows]
    judged = [w for w in windows if w.reason == JUDGED]
    assert len(judged) >= 4 and all(isinstance(w, Window) for w in judged)
    assert judged[-1].grip == pytest.approx(0.9, abs=0.01)
    status = pipeline.status()
    assert status["grip"] == pytest.approx(0.9, abs=0.01)
    assert status["fault"] is None and status["errors"] == {}
    assert status["samples"] == 1000


def test_a_fault_is_reported_once_and_hides_the_grip():
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S, fault_samples=50))
    twin = weak_twin(1.0)
    run(pipeline, twin, 1.0)
    assert pipeline.status()["grip"] is not None
    twin.set_fault("magnet")
    batches = run(pipeline, twin, 1.0, start_s=1.0)
    started = [b.fault_started for b in batches if b.fault_started]
    assert started == ["magnet"]       # once, when it starts
    status = pipeline.status()
    assert status["fault"] == "magnet" and status["grip"] is None


def test_windows_closed_while_faulted_go_out_unjudged():
    # a sensor that stops turning while fed: its windows close 'stuck', a
    # run of them is the 'stuck' fault, and the windows after it go out
    # unjudged, reason FAULT (a subscriber never sees the grip of a fault)
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S))
    twin = SimulatedEms22(sensor_scale=0.0, noise_counts=0)
    batches = run(pipeline, twin, 6.0)
    windows = [w for b in batches for w in b.windows]
    reasons = [w.reason for w in windows]
    assert "stuck" in reasons and FAULT in reasons
    assert reasons.index(FAULT) > reasons.index("stuck")
    assert [b.fault_started for b in batches if b.fault_started] == ["stuck"]
    after = windows[reasons.index(FAULT):]
    assert all(w.reason == FAULT and w.grip is None and w.faulted for w in after)
    assert {w.fault for w in after} == {"stuck"}
    assert {w.fault for w in windows[:reasons.index(FAULT)]} == {None}
    assert pipeline.status()["grip"] is None


def test_a_fault_that_closes_no_window_still_reaches_subscribers_in_one():
    # samples that are all bad close no window: one of no filament carries
    # the fault's name when it starts, and None when it clears
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S, fault_samples=50))
    twin = weak_twin(1.0)
    run(pipeline, twin, 1.0)
    twin.set_fault("magnet")
    faulted = [w for b in run(pipeline, twin, 1.0, start_s=1.0)
               for w in b.windows]
    assert [w.fault for w in faulted] == ["magnet"]     # once
    told = faulted[0]
    assert (told.commanded_mm, told.grip, told.faulted) == (0.0, None, True)
    assert 1.0 < told.end_time == told.start_time < 2.0
    twin.set_fault(None)
    back = [w for b in run(pipeline, twin, 2.0, start_s=2.0) for w in b.windows]
    assert back[0].fault is None and back[0].commanded_mm == 0.0
    assert [w.fault for w in back] == [None] * len(back)
    assert [w.commanded_mm for w in back[1:]].count(0.0) == 0
    assert back[-1].reason == JUDGED


def test_a_print_measurement_stops_on_a_fault_that_closes_no_window():
    # an unplugged sensor (every sample bad) closes no window of its own: the
    # one that brings its fault is what ends MEASURE_MATERIAL_PROFILE_PRINT
    from tests.unit.test_procedure import HARDWARE, KNOWN
    measurement = proc.PrintMeasurement("printed", KNOWN, 0.9, HARDWARE)
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S, fault_samples=50))
    twin = weak_twin(1.0)
    run(pipeline, twin, 1.0)
    twin.set_fault("magnet")
    windows = [w for b in run(pipeline, twin, 1.0, start_s=1.0) for w in b.windows]
    assert [measurement.window(w) for w in windows][-1] == proc.Stop(
        "flow sensor fault: nothing stored")
    # a sensor faulted already: the watch is refused, not started blind
    with pytest.raises(FlowloopError, match="flow sensor filament is faulted"):
        proc.check_sensor("filament", pipeline.status()["fault"])


def test_the_fault_clears_with_the_next_good_samples():
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S, fault_samples=50))
    twin = weak_twin(1.0)
    twin.set_fault("parity")
    run(pipeline, twin, 0.5)
    assert pipeline.fault == "parity"
    twin.set_fault(None)
    run(pipeline, twin, 0.5, start_s=0.5)
    assert pipeline.fault is None
    assert pipeline.status()["errors"]["parity"] == 125


def test_status_is_recomputed_after_each_change_only():
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S))
    first = pipeline.status()
    assert pipeline.status() is first          # nothing changed
    run(pipeline, weak_twin(1.0), 0.2)
    fed = pipeline.status()
    assert fed is not first and fed["samples"] == 50
    pipeline.set_calibration(1.05)
    assert pipeline.status()["calibration"] == 1.05


def test_dump_rows_are_in_extruder_mm_positions_in_sensor_mm():
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S))
    twin = SimulatedEms22(sensor_scale=1.1, noise_counts=0)
    pipeline.set_calibration(1.1)
    assert pipeline.position_at_or_after(0.0) is None   # no sample yet
    batch = run(pipeline, twin, 0.5)[-1]
    rows = batch.dump_rows()
    t, sensor_mm, commanded_mm = rows[-1]
    assert commanded_mm == pytest.approx(SPEED_MM_S * t)
    one_count = 1.0 / ems22.DEFAULT_COUNTS_PER_MM
    assert sensor_mm == pytest.approx(commanded_mm, abs=1.5 * one_count)
    # what the sensor itself measured (calibrations compare it with the
    # extruder's): sensor mm, before the calibration
    assert pipeline.position_at_or_after(t) == pytest.approx(1.1 * sensor_mm, abs=1e-4)
    assert pipeline.position_at_or_after(t + 1.0) is None


def test_a_reverse_sensor_counts_the_filament_forward():
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S, direction_sign=-1.0))
    twin = SimulatedEms22(sensor_scale=-1.0, noise_counts=0)
    run(pipeline, twin, 1.0)
    assert pipeline.status()["grip"] == pytest.approx(1.0, abs=0.01)


def test_windows_get_their_commanded_flows_only_when_a_subscriber_wants_them():
    pipeline = SensorPipeline(Settings(sample_period_s=PERIOD_S))
    twin = weak_twin(1.0)
    plain = [w for b in run(pipeline, twin, 1.0) for w in b.windows
             if w.grip is not None]
    assert plain and all(w.commanded_flows == () for w in plain)
    pipeline.want_flows = True
    rich = [w for b in run(pipeline, twin, 1.0, start_s=1.0) for w in b.windows
            if w.grip is not None]
    assert rich and all(w.commanded_flows for w in rich)
    assert rich[-1].commanded_flows[0] == pytest.approx(SPEED_MM_S * 2.405, rel=0.01)
