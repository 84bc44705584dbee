"""EMS22 frame decoding, the bit-level model, unwrap and MCU record timing."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.sensor import ems22

VECTORS = Path(__file__).resolve().parents[1] / "data" / "ems22_vectors.json"


def build_vectors() -> list:
    """Vectors for C and Python: reads made by the bit-level model in every
    SPI mode, plus hand-made broken reads. Regenerate with
    `python tests/unit/test_ems22.py` after a deliberate change."""
    out = []
    flag_sets = [dict(), dict(mag_inc=True), dict(mag_dec=True),
                 dict(mag_inc=True, mag_dec=True), dict(ocf=False),
                 dict(cof=True), dict(lin=True)]
    for mode in range(4):
        offset = ems22.bit_offset_for_mode(mode)
        for position in (0, 1, 2, 341, 511, 512, 682, 1022, 1023):
            for flags in flag_sets:
                frame = ems22.make_frame(position, **flags)
                for idle in (0, 1):
                    raw = ems22.spi_read_model(frame, mode, idle_do=idle)
                    status = ems22.STATUS_NAMES[ems22.frame_status(frame)]
                    out.append({"raw": raw.hex(), "offset": offset, "mode": mode,
                                "frame": frame, "position": position,
                                "status": status})
    frame = ems22.make_frame(300)
    broken = [("000000", "missing"), ("ffffff", "missing"),
              (f"{(frame ^ 0x0400) << 8:06x}", "parity"),
              (f"{(frame ^ 0x0001) << 8:06x}", "parity")]
    for raw_hex, status in broken:
        word = int(raw_hex, 16)
        out.append({"raw": raw_hex, "offset": 0, "mode": 1, "frame": word >> 8,
                    "position": (word >> 14) & 0x3FF, "status": status})
    return out


def test_shared_vectors_file_is_current():
    assert json.loads(VECTORS.read_text()) == build_vectors()


def test_python_decode_matches_every_shared_vector():
    vectors = json.loads(VECTORS.read_text())
    assert len(vectors) > 500
    for v in vectors:
        frame = ems22.frame_at(bytes.fromhex(v["raw"]), v["offset"])
        assert ems22.STATUS_NAMES[ems22.frame_status(frame)] == v["status"], v
        if v["status"] == "ok":
            assert frame >> ems22.POSITION_SHIFT == v["position"]


def test_frame_layout_by_hand_from_the_datasheet():
    # position 0b1010101010 = 682, OCF=1, others 0: bits 15..1 hold six ones,
    # so even parity leaves P1 = 0.
    frame = 0b1010101010_1_0_0_0_0_0
    assert ems22.make_frame(682) == frame
    assert ems22.frame_status(frame) == ems22.OK
    # one more one in the payload (MagINC) needs P1 = 1
    assert ems22.make_frame(682, mag_inc=True) == frame | 0b100 | 1


def test_spi_mode_offsets_follow_the_clock_edges():
    # mode 1 samples on falling edges after a first rising edge: aligned.
    # mode 2 samples on leading falling edges: one bit late. 0 and 3 sample on
    # the changing edge and read the level from before it: one bit late.
    assert [ems22.bit_offset_for_mode(m) for m in range(4)] == [1, 0, 1, 1]


@given(st.integers(0, 1023), st.integers(0, 3), st.integers(0, 1), st.integers(0, 1))
def test_model_reads_decode_to_the_position_in_every_mode(position, mode, idle, di):
    frame = ems22.make_frame(position)
    raw = ems22.spi_read_model(frame, mode, idle_do=idle, di_level=di)
    got = ems22.frame_at(raw, ems22.bit_offset_for_mode(mode))
    assert got == frame and ems22.frame_status(got) == ems22.OK


@given(st.integers(0, 1023), st.integers(0, 3), st.integers(0, 1))
def test_a_frame_read_one_bit_off_is_never_accepted(position, mode, idle):
    raw = ems22.spi_read_model(ems22.make_frame(position), mode, idle_do=idle)
    offset = ems22.bit_offset_for_mode(mode)
    for wrong in (offset - 1, offset + 1):
        if 0 <= wrong <= 8:
            assert ems22.frame_status(ems22.frame_at(raw, wrong)) != ems22.OK


def _messages(frames, mode=2, first_index=0, tcode=3, first_sequence=0,
              offset=None):
    """What the MCU sends for frames on a bus in `mode`, cutting them at
    `offset` (the configured spi_mode's; by default `mode`'s)."""
    if offset is None:
        offset = ems22.bit_offset_for_mode(mode)
    records = [(tcode, ems22.spi_read_model(f, mode)) for f in frames]
    payloads = ems22.pack_messages(first_index, records, offset)
    return [(first_sequence + i, p) for i, p in enumerate(payloads)]


@settings(max_examples=60)
@given(st.lists(st.integers(-500, 500), min_size=1, max_size=300),
       st.integers(0, 1023))
def test_unwrap_follows_many_turns_both_ways(steps, start):
    truth = start + np.cumsum([0] + steps)
    frames = [ems22.make_frame(int(p) % 1024) for p in truth]
    decoder = ems22.Decoder(bit_offset=1)
    counts = []
    for msg in _messages(frames):  # one message at a time, as they arrive
        counts.extend(decoder.decode([msg]).counts.tolist())
    assert counts == (truth - truth[0]).tolist()


def test_unwrap_over_twenty_turns_forward_then_back():
    path = list(range(0, 20 * 1024, 97)) + list(range(20 * 1024, -3 * 1024, -301))
    decoder = ems22.Decoder(bit_offset=0)
    s = decoder.decode(_messages([ems22.make_frame(p % 1024) for p in path], mode=1))
    assert s.counts.tolist() == path


def test_bad_frames_are_counted_and_skipped_without_losing_position():
    frames = [ems22.make_frame(10), ems22.make_frame(20), 0x0000,
              ems22.make_frame(30) ^ 0x0040, ems22.make_frame(40, mag_inc=True,
                                                            mag_dec=True),
              ems22.make_frame(50, ocf=False), ems22.make_frame(55, cof=True),
              ems22.make_frame(57, lin=True), ems22.make_frame(60)]
    decoder = ems22.Decoder(bit_offset=1)
    s = decoder.decode(_messages(frames))
    assert s.status.tolist() == [ems22.OK, ems22.OK, ems22.MISSING, ems22.PARITY,
                                 ems22.MAGNET, ems22.NOT_READY, ems22.CORDIC,
                                 ems22.LINEARITY, ems22.OK]
    assert s.counts[s.valid].tolist() == [0, 10, 50]
    assert s.error_counts() == {"missing": 1, "parity": 1, "magnet": 1,
                                "not_ready": 1, "cordic_overflow": 1,
                                "linearity": 1}


def test_a_wrong_spi_mode_is_reported_as_misaligned():
    frames = [ems22.make_frame(p) for p in range(0, 600, 7)]
    # spi_mode 1 configured, the bus behaves as mode 2: no frame passes the
    # MCU's check at the configured offset, so every read goes out whole
    messages = _messages(frames, mode=2, offset=0)
    assert all(len(p) > ems22.HEADER_BYTES + ems22.PLAIN_BYTES * 8
               for _, p in messages[:-1])
    s = ems22.Decoder(bit_offset=0).decode(messages)
    assert (s.status == ems22.MISALIGNED).all()


_RECORD = st.one_of(
    st.tuples(st.just("read"), st.integers(0, 1023), st.integers(0, 31),
              st.integers(0, 3), st.integers(0, ems22.TCODE_ERROR - 1)),
    st.tuples(st.just("error"), st.sampled_from([ems22.ERR_SPI_TIME,
                                                 ems22.ERR_SCHEDULE]),
              st.just(0), st.just(0), st.just(0)),
    st.tuples(st.just("raw"), st.integers(0, 0xFFFFFF), st.just(0),
              st.just(0), st.integers(0, ems22.TCODE_ERROR - 1)))


@settings(max_examples=80)
@given(st.lists(_RECORD, min_size=1, max_size=120), st.integers(0, 3))
def test_any_mix_of_records_decodes_as_each_read_alone_would(recs, mode):
    """Plain, whole-read and error records in any order and any message
    cut: each read gets the status of its own frame (or misaligned), and a
    time code exactly when it was not sent plain."""
    offset = ems22.bit_offset_for_mode(mode)
    records, expect_status, expect_tcode = [], [], []
    for kind, a, flags, bus_mode, tcode in recs:
        if kind == "error":
            records.append(ems22.error_record(a))
            expect_status.append({ems22.ERR_SPI_TIME: ems22.SPI_TIME,
                                  ems22.ERR_SCHEDULE: ems22.SCHEDULE}[a])
            expect_tcode.append(ems22.TCODE_ERROR)
            continue
        if kind == "read":
            frame = ems22.make_frame(a, ocf=bool(flags & 16), cof=bool(flags & 8),
                                     lin=bool(flags & 4), mag_inc=bool(flags & 2),
                                     mag_dec=bool(flags & 1))
            raw = ems22.spi_read_model(frame, bus_mode)
        else:
            raw = a.to_bytes(3, "big")
        records.append((tcode, raw))
        status = ems22.frame_status(ems22.frame_at(raw, offset))
        other = ems22.frame_status(ems22.frame_at(raw, 1 - offset))
        if status not in (ems22.OK, ems22.MISSING) and other == ems22.OK:
            status = ems22.MISALIGNED
        plain = status == ems22.OK and tcode < ems22.PLAIN_TCODES
        expect_status.append(status)
        expect_tcode.append(ems22.PLAIN_TCODE if plain else tcode)
    payloads = ems22.pack_messages(0, records, offset)
    assert all(len(p) <= ems22.MAX_MSG_BYTES for p in payloads)
    s = ems22.Decoder(bit_offset=offset).decode(list(enumerate(payloads)))
    assert s.index.tolist() == list(range(len(records)))
    assert s.status.tolist() == expect_status
    assert s.tcode.tolist() == expect_tcode


def test_plain_frames_of_the_first_positions_start_with_a_zero_byte():
    # positions 0..3 put 0x00 in a plain record's first byte: the OCF bit in
    # the second byte tells them from a whole-read or error record
    frames = [ems22.make_frame(p) for p in (0, 1, 2, 3, 2, 1, 0)]
    messages = _messages(frames)
    assert messages[0][1][ems22.HEADER_BYTES] == 0
    assert len(messages[0][1]) == ems22.HEADER_BYTES + 7 * ems22.PLAIN_BYTES
    s = ems22.Decoder().decode(messages)
    assert s.valid.all() and s.counts.tolist() == [0, 1, 2, 3, 2, 1, 0]


def test_a_truncated_record_ends_its_message():
    good = (0, ems22.spi_read_model(ems22.make_frame(5), 2))
    late = (40, good[1])
    payload = ems22.pack_messages(0, [good, late])[0]
    s = ems22.Decoder().decode([(0, payload[:-2])])
    assert s.index.tolist() == [0] and s.valid.all()


def test_mcu_error_records_keep_their_time_slot():
    good = (3, ems22.spi_read_model(ems22.make_frame(5), 2))
    records = [good, ems22.error_record(ems22.ERR_OVERFLOW), good,
               ems22.error_record(ems22.ERR_SPI_TIME),
               ems22.error_record(ems22.ERR_SCHEDULE), good]
    s = ems22.Decoder().decode([(0, p) for p in ems22.pack_messages(0, records)])
    assert s.index.tolist() == [0, 1, 2, 3, 4, 5]
    assert s.status.tolist() == [ems22.OK, ems22.OVERFLOW, ems22.OK, ems22.SPI_TIME,
                                 ems22.SCHEDULE, ems22.OK]
    assert s.error_counts() == {"overflow": 1, "spi_time": 1, "schedule": 1}


def _saturation(overflows, first_index=0):
    """What the MCU sends when its task falls behind after one read:
    `overflows` overflow records, then the read, then 14 more reads."""
    read = (3, ems22.spi_read_model(ems22.make_frame(5), 2))
    records = ([read] + [ems22.error_record(ems22.ERR_OVERFLOW)] * overflows
               + [read] * 15)
    return list(enumerate(ems22.pack_messages(first_index, records)))


def test_a_saturated_overflow_run_loses_time_until_a_new_query():
    # 254 overflow records: the MCU's pending count stopped at 255, so the
    # read after them may belong to any later timer event
    decoder = ems22.Decoder()
    messages = _saturation(ems22.MAX_PENDING - 1)
    s = decoder.decode(messages[:5])   # the run spans messages
    assert not decoder.time_lost and s.valid.sum() == 1
    s = decoder.decode(messages[5:])
    assert decoder.time_lost
    assert s.error_counts()["time_lost"] == 15 and not s.valid.any()
    assert (s.status[s.tcode != ems22.TCODE_ERROR] == ems22.TIME_LOST).all()
    counts = decoder.counts
    decoder.reset()                    # a new query starts counting at 0
    frame = ems22.make_frame(9)
    s = decoder.decode(_messages([frame], tcode=3))
    assert not decoder.time_lost and s.valid.all() and s.index.tolist() == [0]
    # the absolute position carries on across the new query
    assert s.counts.tolist() == [counts + 4]


def test_fewer_overflows_keep_their_time():
    decoder = ems22.Decoder()
    s = decoder.decode(_saturation(ems22.MAX_PENDING - 2))
    assert not decoder.time_lost and s.valid.sum() == 16
    assert s.index[s.valid][1] == 1 + ems22.MAX_PENDING - 2


def test_time_is_rebuilt_exactly_after_a_lost_message():
    per = ems22.RECORDS_PER_MSG
    frames = [ems22.make_frame(p) for p in range(3 * per + 8)]
    msgs = _messages(frames, first_index=65530, first_sequence=7)
    assert [len(p) for _, p in msgs] == [ems22.MAX_BATCH_BYTES] * 3 + [18]
    decoder = ems22.Decoder()
    decoder.next_index = 65530
    s = decoder.decode([msgs[0], msgs[2], msgs[3]])  # msgs[1] dropped by the MCU
    assert s.lost_messages == 1 and s.error_counts() == {"lost_messages": 1}
    expect = (list(range(65530, 65530 + per))
              + list(range(65530 + 2 * per, 65530 + 3 * per + 8)))
    assert s.index.tolist() == expect
    clocks = ems22.sample_clocks(s, start_clock=1000, rest_ticks=16000, time_shift=2)
    # plain records: the read started within PLAIN_TCODES << 2 ticks
    assert clocks[0] == 1000 + 65530 * 16000 + (ems22.PLAIN_TCODE << 2) + 2
    # the absolute encoder loses nothing across the gap
    assert s.counts[per] - s.counts[per - 1] == 2 * per - (per - 1)


def test_a_late_read_keeps_its_time_code():
    # the first tcode too late for a plain record goes out whole
    late = ems22.PLAIN_TCODES
    frames = [ems22.make_frame(p) for p in range(3)]
    for tcode, size in ((late - 1, ems22.PLAIN_BYTES),
                        (late, ems22.READ_RECORD_BYTES)):
        messages = _messages(frames, tcode=tcode)
        assert len(messages[0][1]) == ems22.HEADER_BYTES + 3 * size
    s = ems22.Decoder().decode(messages)
    assert s.valid.all() and s.tcode.tolist() == [late] * 3
    clocks = ems22.sample_clocks(s, start_clock=1000, rest_ticks=16000, time_shift=2)
    assert clocks[1] == 1000 + 16000 + (late << 2) + 2


# 1 ms reads of the default shaft: 120 mm/s is 12.3 counts per read
LIMIT = ems22.max_counts_per_record(0.001, ems22.DEFAULT_COUNTS_PER_MM)


def _checked(frames_or_none):
    """Decode one frame per record (None: a missing read), limits on."""
    frames = [0xFFFF if f is None else f for f in frames_or_none]
    return ems22.Decoder(max_counts_per_record=LIMIT).decode(_messages(frames))


def test_a_fast_retraction_across_a_long_gap_is_a_break_not_a_silent_turn():
    # 10 reads moving 3 counts each, then 60 missing reads in which a fast
    # retraction pulls 600 counts back: the short way round says +424
    path = [3 * i for i in range(10)] + [None] * 60 + [27 - 600, 27 - 597]
    s = _checked([None if p is None else ems22.make_frame(p % 1024)
                  for p in path])
    good = np.flatnonzero(s.valid)
    assert s.breaks[good].tolist() == [False] * 10 + [True, False]
    assert s.error_counts()["discontinuity"] == 1
    # after the break the position follows again from the new read
    assert s.counts[good[-1]] - s.counts[good[-2]] == 3


def test_a_short_gap_still_unwraps_across_a_wrap():
    # 5 missing reads at 10 counts per read: 60 counts, well inside a half turn
    path = [1000 + 10 * i for i in range(5)] + [None] * 5 + [1100]
    s = _checked([None if p is None else ems22.make_frame(p % 1024)
                  for p in path])
    assert not s.breaks.any()
    assert s.counts[s.valid].tolist() == [0, 10, 20, 30, 40, 100]


@given(st.sampled_from([(6, 7), (6, 9), (8, 9), (5, 8)]),
       st.integers(0, 1023))
def test_two_flipped_bits_that_parity_misses_are_rejected_as_a_jump(bits, p0):
    bad = ems22.make_frame(p0) ^ (1 << (bits[0] + 6)) ^ (1 << (bits[1] + 6))
    assert ems22.frame_status(bad) == ems22.OK      # parity cannot see it
    frames = [ems22.make_frame((p0 + i) % 1024) for i in range(3)]
    s = _checked(frames[:2] + [bad] + frames[2:])
    assert s.status.tolist() == [ems22.OK, ems22.OK, ems22.JUMP, ems22.OK]
    assert s.counts[s.valid].tolist() == [0, 1, 2]
    assert s.error_counts() == {"jump": 1}


def test_the_first_read_of_a_new_query_is_a_break():
    decoder = ems22.Decoder(max_counts_per_record=LIMIT)
    decoder.decode(_messages([ems22.make_frame(5), ems22.make_frame(6)]))
    decoder.reset()
    s = decoder.decode(_messages([ems22.make_frame(400), ems22.make_frame(401)]))
    assert s.breaks.tolist() == [True, False]


def test_the_largest_sample_period_keeps_unwrapping_sure():
    # even a missed read at the longest period stays inside half a turn
    longest = ems22.SAMPLE_PERIOD_RANGE_S[1]
    per_read = ems22.max_counts_per_record(longest, ems22.DEFAULT_COUNTS_PER_MM)
    assert 2 * per_read < ems22.POSITIONS // 2


def test_print_times_follow_a_linear_clock_conversion():
    clocks = np.array([16000.0, 32000.0, 1e9])
    times = ems22.print_times(clocks, lambda clock: 0.5 + clock / 16e6)
    assert times == pytest.approx([0.501, 0.502, 0.5 + 1e9 / 16e6])


def test_time_shift_covers_two_milliseconds_of_ticks():
    shift = ems22.time_shift_for(16e6)
    assert (254 << shift) / 16e6 >= 0.002 > (254 << (shift - 1)) / 16e6


def _status(codes):
    z = np.zeros(len(codes), dtype=np.int64)
    return ems22.Samples(z, z, np.array(codes, dtype=np.int64), z)


def test_transient_errors_are_counted_but_never_a_fault():
    monitor = ems22.FaultMonitor(limit=5)
    for _ in range(50):
        assert monitor.update(_status([ems22.PARITY] * 4 + [ems22.OK])) is None
    assert monitor.fault is None and monitor.errors == {"parity": 200}


def test_consecutive_bad_samples_across_batches_raise_one_fault_then_clear():
    monitor = ems22.FaultMonitor(limit=5)
    assert monitor.update(_status([ems22.OK, ems22.MISSING, ems22.MISSING])) is None
    assert monitor.update(_status([ems22.MISSING] * 3)) == "missing"
    assert monitor.update(_status([ems22.MISSING] * 30)) is None  # same episode
    assert monitor.fault == "missing" and monitor.episodes == 1
    monitor.update(_status([ems22.OK]))
    assert monitor.fault is None


def test_two_stuck_windows_make_a_stuck_fault_a_judged_one_clears_it():
    monitor = ems22.FaultMonitor()
    assert monitor.note_window("stuck") is None
    assert monitor.note_window("stuck") == "stuck"
    monitor.update(_status([ems22.OK] * 3))
    assert monitor.fault == "stuck"
    monitor.note_window("judged")
    assert monitor.fault is None and monitor.errors == {"stuck": 2}


def test_the_docs_name_every_error_kind():
    doc = (Path(__file__).resolve().parents[2] / "docs" / "flow_sensor.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| `errors` |"))
    named = row.split("by kind:")[1].strip(" |").split(", ")
    assert named == [*ems22.STATUS_NAMES[1:], "stuck", "lost_messages",
                     "discontinuity"]


def test_default_counts_per_mm_is_the_3_17mm_axle():
    assert ems22.DEFAULT_COUNTS_PER_MM == pytest.approx(102.823, abs=1e-3)
    assert 1024 / ems22.DEFAULT_COUNTS_PER_MM == pytest.approx(math.pi * 3.17)


if __name__ == "__main__":
    VECTORS.write_text(json.dumps(build_vectors(), indent=0) + "\n")
    print(f"wrote {VECTORS}")


@settings(max_examples=200)
@given(st.lists(st.booleans(), min_size=1, max_size=300), st.integers(1, 20),
       st.lists(st.integers(1, 40), min_size=1, max_size=20))
def test_faults_follow_runs_of_bad_samples_however_batches_are_cut(bad, limit, cuts):
    # reference: a fault starts when `limit` bad samples in a row are seen and
    # clears at the next good one
    monitor, run, expect, i = ems22.FaultMonitor(limit), 0, None, 0
    for size in cuts * (len(bad) // sum(cuts) + 1):
        part = bad[i:i + size]
        if not part:
            break
        status = np.where(part, ems22.MISSING, ems22.OK)
        n = len(part)
        monitor.update(ems22.Samples(np.arange(n), np.zeros(n, int), status,
                                     np.zeros(n, int)))
        for b in part:
            run = run + 1 if b else 0
            expect = "missing" if run >= limit else (expect if b else None)
        assert monitor.fault == expect
        i += size
    assert monitor.errors.get("missing", 0) == sum(bad)


def test_one_overflow_record_counts_its_missed_reads():
    read = (3, ems22.spi_read_model(ems22.make_frame(5), 2))
    records = [read, ems22.error_record(ems22.ERR_OVERFLOW, 7), read]
    s = ems22.Decoder().decode(list(enumerate(ems22.pack_messages(0, records))))
    # the read after it keeps its time: record slot 8, not 2
    assert s.index.tolist() == list(range(9))
    assert s.error_counts() == {"overflow": 7}
    assert s.status[8] == ems22.OK


def test_an_overflow_record_of_254_reads_loses_time():
    read = (3, ems22.spi_read_model(ems22.make_frame(5), 2))
    records = [read, ems22.error_record(ems22.ERR_OVERFLOW,
                                        ems22.MAX_PENDING - 1), read]
    decoder = ems22.Decoder()
    s = decoder.decode(list(enumerate(ems22.pack_messages(0, records))))
    assert decoder.time_lost and s.status[-1] == ems22.TIME_LOST


def test_software_spi_refuses_the_modes_it_cannot_read_in():
    from flowloop.sensor.ems22 import SOFTWARE_SPI_MODES, software_spi_mode_problem
    assert SOFTWARE_SPI_MODES == (1, 2)
    assert software_spi_mode_problem(ems22.DEFAULT_SPI_MODE) is None
    assert software_spi_mode_problem(1) is None
    for mode in (0, 3):
        problem = software_spi_mode_problem(mode)
        assert f"spi_mode {mode} cannot read" in problem and "use spi_mode 2" in problem
