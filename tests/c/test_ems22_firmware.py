"""mcu_sensor/sensor_ems22.c itself, run on the host (ems22_firmware_test.c
with stand-ins for the Klipper calls it makes), its messages decoded by
flowloop.sensor.ems22: the host's decoder models exactly what the firmware sends,
and rebuilds each read's time from it."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from flowloop.sensor import ems22

HERE = Path(__file__).resolve().parent
TICKS_PER_US = 16                     # klipper_stubs/board/misc.h
REST = 1000 * TICKS_PER_US            # 1 ms
SHIFT = ems22.time_shift_for(TICKS_PER_US * 1e6)
START = 1000
SPI_TICKS = 24 * TICKS_PER_US         # 24 clocks at 1 MHz
# what the host sends for a 1 MHz hardware bus on this MCU, in spi_mode 2
MAX_READ = ems22.max_read_ticks(1_000_000, False, TICKS_PER_US * 1e6)
OFFSET = ems22.bit_offset_for_mode(2)
# how far off the host may time a plain record's read (see sample_clocks)
PLAIN_TOLERANCE = (ems22.PLAIN_TCODES << SHIFT) / 2 + (1 << SHIFT)
# records per message at REST: the firmware sends a message when it is full
PER = ems22.records_per_message(REST, TICKS_PER_US * 1e6)


@pytest.fixture(scope="module")
def firmware(compile_c):
    exe = compile_c("ems22_firmware_test.c", HERE / "klipper_stubs")

    def run(script, max_read_ticks=MAX_READ, bit_offset=OFFSET, config=None):
        if config is None:
            config = f"c {max_read_ticks} {bit_offset}\n"
        out = subprocess.run([str(exe)], input=config + script,
                             capture_output=True, text=True)
        assert out.returncode == 0, out.stdout
        return [(int(seq), bytes.fromhex(data)) for _, seq, data in
                (line.split() for line in out.stdout.splitlines())]
    run.exe = exe
    return run


def test_a_bus_without_a_cs_pin_is_refused_at_config(firmware):
    # as Klipper's sensor_angle.c: the chip latches its frame on CS rising
    out = subprocess.run([str(firmware.exe)], input=f"n\nc {MAX_READ} {OFFSET}\n",
                         capture_output=True, text=True)
    assert (out.returncode, out.stdout) == (2, "shutdown ems22 requires cs pin\n")
    assert firmware("") == []   # with one, config_ems22 passes


def _query(rest=REST):
    """query_ems22 as the host sends it (the batch size is the host's)."""
    max_bytes = ems22.message_bytes(rest, TICKS_PER_US * 1e6)
    return f"q {START} {rest} {SHIFT} {max_bytes}\n"


def _raw(position):
    return ems22.spi_read_model(ems22.make_frame(position), 2).hex()


def _reads(delays, positions=None, spi_ticks=SPI_TICKS):
    positions = positions or range(len(delays))
    return "".join(f"t 1\nr {d} {spi_ticks} {_raw(p)}\n"
                   for d, p in zip(delays, positions))


def _record_counts(messages):
    return [len(ems22.parse_records(p[ems22.HEADER_BYTES:], OFFSET)[0])
            for _, p in messages]


def _decode(messages, decoder=None):
    decoder = decoder or ems22.Decoder(bit_offset=OFFSET)
    return decoder.decode(messages)


def test_reads_are_timed_within_half_a_tcode_step(firmware):
    # the MCU truncates the delay to tcode << SHIFT; the host takes the
    # middle. A good read on time is plain: within PLAIN_TCODES << SHIFT.
    delays = np.random.default_rng(5).integers(0, REST - SPI_TICKS, 36)
    delays[:6] = [0, 1, (ems22.PLAIN_TCODES << SHIFT) - 1,
                  ems22.PLAIN_TCODES << SHIFT, 100, 700]
    messages = firmware(_query()
                        + _reads(delays.tolist(), range(0, 36 * 30, 30)))
    assert all(len(p) <= ems22.MAX_MSG_BYTES for _, p in messages)
    s = _decode(messages)
    assert s.valid.all() and s.index.tolist() == list(range(36))
    assert s.counts.tolist() == list(range(0, 36 * 30, 30))
    plain = delays < ems22.PLAIN_TCODES << SHIFT
    assert plain[:6].tolist() == [True, True, True, False, True, True]
    assert (s.tcode[plain] == ems22.PLAIN_TCODE).all()
    clocks = ems22.sample_clocks(s, START, REST, SHIFT)
    error = np.abs(clocks - (START + np.arange(36) * REST + delays))
    assert error[~plain].max() <= (1 << SHIFT) / 2
    assert error[plain].max() <= PLAIN_TOLERANCE


@pytest.mark.parametrize("period_us", [200, 1000, 3000, 7000, 25000])
def test_a_batch_is_sent_before_its_first_read_waits_20ms(firmware, period_us):
    # the host's batch size, as the firmware applies it
    rest = period_us * TICKS_PER_US
    messages = firmware(_query(rest) + _reads([50] * 120))
    counts = _record_counts(messages)
    assert sum(counts) == 120 - 120 % counts[0]
    for n in counts:
        assert (n - 1) * period_us < 20000
        assert n == ems22.RECORDS_PER_MSG or n * period_us >= 20000


def test_missed_timer_events_keep_their_slots_as_overflow_records(firmware):
    script = (_query() + _reads([100], [7])
              + f"t 3\nr 900 {SPI_TICKS} {_raw(9)}\n" + _reads([100] * (PER - 3)))
    messages = firmware(script)
    # one record counts both missed events
    tcodes = ems22.parse_records(messages[0][1][ems22.HEADER_BYTES:], OFFSET)[0]
    assert tcodes.count(ems22.TCODE_ERROR) == 1
    s = _decode(messages)
    assert s.status[:4].tolist() == [ems22.OK, ems22.OVERFLOW, ems22.OVERFLOW,
                                     ems22.OK]
    # the read after the overflows belongs to the latest of the three events
    clock = ems22.sample_clocks(s, START, REST, SHIFT)[3]
    assert abs(clock - (START + 3 * REST + 900)) <= PLAIN_TOLERANCE


def test_slow_spi_and_late_reads_become_error_records(firmware):
    slow = MAX_READ + 1                    # longer than the host allows
    late = ems22.TCODE_ERROR << SHIFT      # no tcode left to say when
    script = (_query()
              + _reads([0, 0, late - 1, late, 0], spi_ticks=SPI_TICKS)
              .replace(f"r 0 {SPI_TICKS} ", f"r 0 {slow} ", 1)
              + _reads([0] * (PER - 5)))
    s = _decode(firmware(script))
    assert s.status[:5].tolist() == [ems22.SPI_TIME, ems22.OK, ems22.OK,
                                     ems22.SCHEDULE, ems22.OK]
    assert s.tcode[2] == ems22.TCODE_ERROR - 1


def test_a_task_too_far_behind_loses_time_until_the_query_restarts(firmware):
    # 300 timer events before the task runs: the pending count stops at 255,
    # so the firmware counts 254 overflow slots for 299 missed events
    behind = 300
    script = (_query() + _reads([100])
              + f"t {behind}\nr 100 {SPI_TICKS} {_raw(3)}\n"
              + _reads([100] * (PER - 3)))
    messages = firmware(script)
    # in one record: a stall costs one message, not 21 the serial link drops
    assert len(messages) == 1
    decoder = ems22.Decoder(bit_offset=1)
    s = _decode(messages, decoder)
    assert s.error_counts()["overflow"] == ems22.MAX_PENDING - 1
    # the read after the run is record 255 but was made for timer event 300
    assert s.status[ems22.MAX_PENDING - 1] == ems22.OVERFLOW
    assert s.index[ems22.MAX_PENDING] == ems22.MAX_PENDING < behind
    # the host knows the times after the run are lost, and never uses them
    assert decoder.time_lost and s.valid.sum() == 1
    assert (s.status[ems22.MAX_PENDING:] == ems22.TIME_LOST).all()
    # a new query starts the MCU's count again: times are right from there
    decoder.reset()
    s = _decode(firmware(_query() + _reads([100] * PER)),
                decoder)
    assert s.valid.all() and not decoder.time_lost
    truth = START + np.arange(PER) * REST + 100
    assert np.abs(ems22.sample_clocks(s, START, REST, SHIFT) - truth).max() <= (
        PLAIN_TOLERANCE)


def test_rest_ticks_zero_stops_the_reads(firmware):
    script = (_query() + _reads([0] * 5)
              + "q 0 0 0 0\n" + _reads([0] * 20))
    assert firmware(script) == []


@pytest.mark.parametrize("speed_hz, software", [(1_000_000, False),
                                                (100_000, False),
                                                (1_000_000, True)])
def test_the_read_time_limit_the_host_sends_passes_a_read_on_that_bus(
        firmware, speed_hz, software):
    # a read as long as the bus makes it is trusted; twice as long is not
    limit = ems22.max_read_ticks(speed_hz, software, TICKS_PER_US * 1e6)
    read = int(ems22.read_time_s(speed_hz, software, TICKS_PER_US * 1e6)
               * TICKS_PER_US * 1e6)
    script = (_query() + _reads([0] * (PER - 2))
              + _reads([0], spi_ticks=read) + _reads([0], spi_ticks=2 * limit))
    s = _decode(firmware(script, max_read_ticks=limit))
    assert s.status[-2:].tolist() == [ems22.OK, ems22.SPI_TIME]


def test_a_batch_size_beyond_the_buffer_is_clamped(firmware):
    # and a whole-read record after a full batch's worth still fits
    records = _reads([0] * (ems22.RECORDS_PER_MSG - 1)) + _reads([0], [900])
    script = f"q {START} {REST} {SHIFT} 255\n" + records.replace(
        _raw(900), "ffffff")
    sizes = [len(p) for _, p in firmware(script)]
    assert sizes == [ems22.MAX_BATCH_BYTES - ems22.PLAIN_BYTES
                     + ems22.READ_RECORD_BYTES]
    assert sizes[0] <= ems22.MAX_MSG_BYTES
    script = f"q {START} {REST} {SHIFT} 255\n" + _reads([0] * 60)
    sizes = [len(p) for _, p in firmware(script)]
    full = ems22.HEADER_BYTES + ems22.RECORDS_PER_MSG * ems22.PLAIN_BYTES
    assert full == ems22.MAX_BATCH_BYTES
    assert sizes == [full] * 2
