"""The simulated EMS22: melt-limited grip, counts, and real-format messages."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.material.profile import FlowLine, Line
from flowloop.sensor import ems22
from flowloop.sensor.grip import GripEstimator
from flowloop.sensor.twin import SimulatedEms22, melt_grip, raw_reads


def _melt(slope, temp_c, flow):
    return FlowLine(slope_mm3_s_per_c=slope, temp_c=temp_c, flow_mm3_s=flow).line()


def test_the_twin_melts_what_the_material_line_gives():
    melt = _melt(0.25, 210, 12)
    assert isinstance(melt, Line)
    assert melt_grip(melt, 6, 210) == 1.0
    assert melt_grip(melt, 24, 210) == pytest.approx(0.5)
    assert melt_grip(melt, 17, 230) == pytest.approx(1.0)
    assert melt_grip(melt, 34, 230) == pytest.approx(0.5)
    # below the line's zero nothing melts
    assert melt_grip(melt, 5, 100) == 0.0


def test_the_twin_takes_any_material_line_object():
    # a profile's working line is what a hotend twin will be handed
    sim = SimulatedEms22(Line(0.1, -10.0), noise_counts=0)
    assert sim.melt.flow_mm3_s(200) == pytest.approx(10.0)


@given(st.integers(0, 0xFFFF), st.integers(0, 3), st.integers(0, 1))
def test_bulk_reads_match_the_edge_by_edge_model(frame, mode, idle):
    offset = ems22.bit_offset_for_mode(mode)
    fast = raw_reads(np.array([frame]), offset, idle_do=idle)[0]
    assert bytes(fast) == ems22.spi_read_model(frame, mode, idle_do=idle)


def _run(sim, speed_mm_s, seconds, temp_c, period=0.001):
    times = np.arange(0, seconds, period)
    commanded = speed_mm_s * times
    messages = sim.messages(times, commanded, temp_c)
    samples = ems22.Decoder(bit_offset=sim.bit_offset).decode(messages)
    return times, commanded, samples


def test_decoded_twin_counts_follow_the_filament_within_noise():
    sim = SimulatedEms22(noise_counts=0.34, seed=3)
    times, commanded, samples = _run(sim, 2.0, 2.0, 210)
    assert samples.valid.all()
    measured = samples.counts / sim.counts_per_mm
    assert np.abs(measured - commanded).max() < 2.5 / sim.counts_per_mm


@pytest.mark.parametrize("temp_c, expect", [(200, 0.5), (250, 1.0), (225, 0.75)])
def test_grip_falls_when_demand_exceeds_what_melts(temp_c, expect):
    # 8.316 mm/s of 1.75 mm filament = 20 mm^3/s; 200 C melts 10, 250 C 20
    sim = SimulatedEms22(_melt(0.2, 200, 10), seed=1)
    times, commanded, samples = _run(sim, 20 / 2.405, 3.0, temp_c)
    est = GripEstimator(window_mm=1.25)
    est.add(times, samples.counts / sim.counts_per_mm, commanded)
    assert est.grip == pytest.approx(expect, abs=0.02)


def test_simulated_faults_come_out_as_decoder_errors():
    sim = SimulatedEms22()
    for fault, status in (("missing", ems22.MISSING), ("magnet", ems22.MAGNET),
                          ("parity", ems22.PARITY)):
        sim.set_fault(fault)
        _, _, samples = _run(sim, 1.0, 0.05, 210)
        assert (samples.status == status).all()
    with pytest.raises(FlowloopError):
        sim.set_fault("gremlins")


def test_messages_continue_indices_and_sequences_across_calls():
    sim = SimulatedEms22(noise_counts=0)
    first = sim.messages([0.0, 0.001, 0.002], [0, 0, 0], 210)
    second = sim.messages([0.003], [0.1], 210)
    assert [seq for seq, _ in first + second] == [0, 1]
    decoder = ems22.Decoder(bit_offset=sim.bit_offset)
    assert decoder.decode(first + second).index.tolist() == [0, 1, 2, 3]
