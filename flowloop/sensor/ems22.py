"""Bourns EMS22A magnetic encoder: the MCU protocol flowloop's firmware
speaks, a bit-level model of the chip's serial output, and the decoder.

The message formats are shared by the klippy adapters (to look the commands
up) and by the firmware check that tells users to rebuild. The record layout
and frame checks mirror mcu_sensor/ems22_frame.h; tests/data/ems22_vectors.json
holds vectors that both the C header and this module are tested against.

Frame alignment (see docs/flow_sensor.md): the chip drives a new bit on DO
at each rising CLK edge, valid 375 ns later, D9 first; CLK idles high and
runs at 1 MHz at most. A master must therefore sample on falling edges, half
a period (>= 500 ns) after the change. SPI mode 2 (CPOL=1, CPHA=0) does that
with the clock idling high as the datasheet wants, and its first falling edge
comes half a period after the transfer starts, honouring the 500 ns from
CSn low to the first falling edge; it sees the frame one bit late (its first
sample precedes D9), so the firmware clocks 24 bits and the host takes the
16-bit frame at bit offset 1. Mode 1 (CPOL=0, what ddPrint used) sees it at
offset 0; modes 0 and 3 sample on the very edge where DO changes and get
the previous bit, which the model treats as offset 1 but which depends on
hold time: they are allowed, not advised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import FlowloopError
from ..window import JUDGED, STUCK

CONFIG_CMD = ("config_ems22 oid=%c spi_oid=%c max_read_ticks=%u"
              " bit_offset=%c")
QUERY_CMD = ("query_ems22 oid=%c clock=%u rest_ticks=%u time_shift=%c"
             " max_bytes=%c")
BULK_DATA_MSG = "sensor_bulk_data oid=%c sequence=%hu data=%*s"

# --- mirrors mcu_sensor/ems22_frame.h ----------------------------------------
READ_BYTES = 3
HEADER_BYTES = 2
# Records (see the header): plain (a good frame read on time), a whole read
# with its time code, an MCU error; the last two start 0x00, kind < OCF
PLAIN_BYTES = 2
READ_RECORD_BYTES = 2 + 1 + READ_BYTES
ERROR_RECORD_BYTES = 4
KIND_READ, KIND_ERROR = 1, 2
MAX_MSG_BYTES = 51
# A message is sent once it holds this many bytes (or the host's fewer), so
# any record still fits before it is
MAX_BATCH_BYTES = MAX_MSG_BYTES - READ_RECORD_BYTES + 1
# The most records a message holds (all plain)
RECORDS_PER_MSG = (MAX_BATCH_BYTES - HEADER_BYTES + PLAIN_BYTES - 1) // PLAIN_BYTES
# No record waits longer than this in the MCU (goal: 30 ms at the host)
MAX_BATCH_AGE_S = 0.020
TCODE_ERROR = 0xFF
# A plain record's read started within this many tcode units; the host
# times it at PLAIN_TCODE (+ half a unit, see sample_clocks): about the middle
PLAIN_TCODES = 16
PLAIN_TCODE = PLAIN_TCODES // 2 - 1
ERR_OVERFLOW, ERR_SCHEDULE, ERR_SPI_TIME = 1, 2, 3
# The firmware's count of unread timer events stops here: a task that falls
# further behind loses count of them (see Decoder, time_lost)
MAX_PENDING = 255

POSITION_SHIFT = 6
POSITIONS = 1024
OCF, COF, LIN, MAGINC, MAGDEC = 1 << 5, 1 << 4, 1 << 3, 1 << 2, 1 << 1

OK, MISSING, PARITY, NOT_READY, CORDIC, LINEARITY, MAGNET = range(7)
# Host-only sample states (after the frame states of the header)
MISALIGNED, OVERFLOW, SCHEDULE, SPI_TIME, TIME_LOST, JUMP = 7, 8, 9, 10, 11, 12
STATUS_NAMES = ("ok", "missing", "parity", "not_ready", "cordic_overflow",
                "linearity", "magnet", "misaligned", "overflow", "schedule",
                "spi_time", "time_lost", "jump")
_MCU_ERRORS = {ERR_OVERFLOW: OVERFLOW, ERR_SCHEDULE: SCHEDULE,
               ERR_SPI_TIME: SPI_TIME}

# 3.17 mm (1/8") D-shaft pressed on the filament: 1024 counts per pi*3.17 mm
SHAFT_DIAMETER_MM = 3.17
DEFAULT_COUNTS_PER_MM = POSITIONS / (math.pi * SHAFT_DIAMETER_MM)
MAX_SPI_HZ = 1_000_000
MIN_SPI_HZ = 100_000
# [flow_sensor] options and their limits: the adapter reads them from here
DEFAULT_SPI_MODE = 2
DEFAULT_SAMPLE_PERIOD_S = 0.004
DEFAULT_FAULT_SAMPLES = 100
# The fastest plausible filament motion (a fast bowden retraction). A gap
# between good reads in which it could turn the shaft half a turn (4.98 mm)
# makes unwrapping ambiguous; a step faster than it is a bad read.
MAX_FILAMENT_SPEED_MM_S = 120.0
# Below the half turn with room for a few missed reads: at 120 mm/s a 10 ms
# period is 1.2 mm (a quarter of the half turn) per read.
SAMPLE_PERIOD_RANGE_S = (0.0002, 0.01)
# Reading noise and quantisation allowed on top of the fastest motion
JUMP_MARGIN_COUNTS = 4


def parity_odd(frame: int) -> int:
    """1 when the 16-bit frame has an odd number of ones (parity error)."""
    return bin(frame & 0xFFFF).count("1") & 1


def parity_bits(frames: np.ndarray) -> np.ndarray:
    """parity_odd of each 16-bit frame of an integer array."""
    parity = np.array(frames, dtype=np.int64)
    for shift in (8, 4, 2, 1):
        parity ^= parity >> shift
    return parity & 1


def make_frame(position: int, ocf: bool = True, cof: bool = False,
               lin: bool = False, mag_inc: bool = False,
               mag_dec: bool = False) -> int:
    """The 16-bit frame the chip sends, with even parity in bit 0."""
    frame = (position % POSITIONS) << POSITION_SHIFT
    for flag, bit in ((ocf, OCF), (cof, COF), (lin, LIN), (mag_inc, MAGINC),
                      (mag_dec, MAGDEC)):
        if flag:
            frame |= bit
    return frame | parity_odd(frame)


def frame_at(raw: Sequence[int], offset: int) -> int:
    """The frame whose first bit is bit `offset` (0..8) of a 24-bit read."""
    word = (raw[0] << 16) | (raw[1] << 8) | raw[2]
    return (word >> (8 - offset)) & 0xFFFF


def frame_status(frame: int) -> int:
    """OK or the first failed check, in the order of ems22_frame_check()
    (looked up: the twin packs every sample it simulates through this)."""
    return int(_STATUS_OF_FRAME[frame & 0xFFFF])


def frame_statuses(frames: np.ndarray) -> np.ndarray:
    """frame_status of each frame of an integer array (what Decoder uses)."""
    status = np.full(len(frames), OK, dtype=np.int64)
    checks = (
        ((frames & MAGINC) != 0) & ((frames & MAGDEC) != 0), MAGNET,
        (frames & LIN) != 0, LINEARITY,
        (frames & COF) != 0, CORDIC,
        (frames & OCF) == 0, NOT_READY,
        parity_bits(frames) != 0, PARITY,
        (frames == 0) | (frames == 0xFFFF), MISSING,
    )
    # Later checks win, so apply them from the least to the most basic.
    for i in range(0, len(checks), 2):
        status[checks[i]] = checks[i + 1]
    return status


# Every 16-bit frame's status, looked up instead of computed per batch (the
# host decodes ~10 batches a second; a lookup is one numpy operation)
_STATUS_OF_FRAME = frame_statuses(np.arange(1 << 16, dtype=np.int64))


# --- bit-level model of the chip on the wire ---------------------------------

def spi_read_model(frame: int, spi_mode: int, nbytes: int = READ_BYTES,
                   di_level: int = 0, idle_do: int = 1) -> bytes:
    """What an SPI master in `spi_mode` reads from the chip, edge by edge.

    The chip: CSn low latches the frame; each rising CLK edge drives the next
    bit on DO (D9 first; after 16 bits, the DI level), valid 375 ns later.
    Before the first rising edge DO shows `idle_do`. The master: CPOL sets
    the idle level, CPHA=0 samples on the leading edge of each clock, CPHA=1
    on the trailing one. A sample on the edge where DO changes reads the old
    level, since the new one is not valid until 375 ns later.
    """
    if spi_mode not in (0, 1, 2, 3):
        raise FlowloopError(f"spi_mode must be 0..3, not {spi_mode}")
    cpol, cpha = spi_mode >> 1, spi_mode & 1
    do_level, rises, bits = idle_do, 0, []
    clk = cpol
    for _ in range(nbytes * 8):
        for edge in (0, 1):  # leading, trailing
            clk ^= 1
            sample_now = edge == cpha
            if sample_now:
                bits.append(do_level)  # read before any change at this edge
            if clk == 1:  # rising edge: the chip drives its next bit
                do_level = (frame >> (15 - rises)) & 1 if rises < 16 else di_level
                rises += 1
    value = 0
    for bit in bits:
        value = (value << 1) | bit
    return value.to_bytes(nbytes, "big")


# The modes in which Klipper's software SPI (src/spi_software.c) reads the
# frame where flowloop decodes it: it samples MISO half a clock after the
# leading edge (modes 0, 2) or just after the trailing edge (1, 3), so in
# mode 0 it reads the bit the chip drives on that same rising edge and in
# mode 3 the next one. Those two fault as `misaligned` (never a wrong
# position), shown on the simulated firmware (tests/fil/test_fil_spi_modes.py).
SOFTWARE_SPI_MODES = (1, 2)


def software_spi_mode_problem(spi_mode: int) -> Optional[str]:
    """Why spi_mode cannot read an EMS22 on Klipper's software SPI, or None."""
    if spi_mode in SOFTWARE_SPI_MODES:
        return None
    return (f"spi_mode {spi_mode} cannot read an EMS22 on software SPI (Klipper's "
            f"software SPI samples MISO on another edge than the hardware bus); "
            f"use spi_mode 2 (the default) or 1")


def bit_offset_for_mode(spi_mode: int) -> int:
    """Where the frame starts in a read, per the model above."""
    probe = make_frame(0x2A5)
    raw = spi_read_model(probe, spi_mode)
    for offset in range(9):
        if frame_at(raw, offset) == probe:
            return offset
    raise AssertionError("model lost the frame")  # pragma: no cover


# --- MCU record packing (what sensor_ems22.c sends) --------------------------

def pack_messages(first_index: int, records: Sequence[Tuple[int, bytes]],
                  bit_offset: int = 1,
                  max_bytes: int = MAX_MSG_BYTES) -> List[bytes]:
    """sensor_bulk_data payloads for (tcode, 3-byte read) records and
    error_record()s, as sensor_ems22.c packs them: a 2-byte little-endian
    first-record index, then a plain record for a good frame (at
    bit_offset) read within PLAIN_TCODES, a whole-read record otherwise.
    A message is sent once it holds max_bytes (at most MAX_BATCH_BYTES)."""
    out: List[bytes] = []
    payload = bytearray()
    index = first_index
    max_bytes = min(max_bytes, MAX_BATCH_BYTES)
    for tcode, raw in records:
        if tcode == TCODE_ERROR:
            rec = bytes((0, KIND_ERROR, raw[0], raw[1]))
        else:
            frame = frame_at(raw, bit_offset)
            if tcode < PLAIN_TCODES and frame_status(frame) == OK:
                rec = frame.to_bytes(2, "big")
            else:
                rec = bytes((0, KIND_READ, tcode)) + bytes(raw)
        if not payload:
            payload += (index & 0xFFFF).to_bytes(2, "little")
        payload += rec
        index += int(record_slots_of(tcode, raw))
        if len(payload) >= max_bytes:
            out.append(bytes(payload))
            payload = bytearray()
    if payload:
        out.append(bytes(payload))
    return out


def error_record(code: int, count: int = 1) -> Tuple[int, bytes]:
    """An MCU error record; an overflow record counts the timer events
    (record slots) it stands for."""
    return TCODE_ERROR, bytes((code, count if code == ERR_OVERFLOW else 0, 0))


def record_slots_of(tcode, raw) -> int:
    """Timer events (record indices) a record stands for: an overflow
    record its count, every other record one."""
    if tcode == TCODE_ERROR and raw[0] == ERR_OVERFLOW:
        return max(raw[1], 1)
    return 1


def parse_records(body: bytes, bit_offset: int) -> Tuple[List[int], List[int]]:
    """(tcodes, 24-bit words) of a message body's records, one per record:
    a plain record's frame placed at bit_offset of its word, an error
    record's code and count in the word's top two bytes (tcode
    TCODE_ERROR). A malformed record ends the body."""
    tcodes: List[int] = []
    words: List[int] = []
    shift = 8 - bit_offset
    i, n = 0, len(body)
    while i + 1 < n:
        b0, b1 = body[i], body[i + 1]
        if b0 or b1 >= OCF:
            tcodes.append(PLAIN_TCODE)
            words.append(((b0 << 8) | b1) << shift)
            i += PLAIN_BYTES
        elif b1 == KIND_READ and i + READ_RECORD_BYTES <= n:
            tcodes.append(body[i + 2])
            words.append((body[i + 3] << 16) | (body[i + 4] << 8) | body[i + 5])
            i += READ_RECORD_BYTES
        elif b1 == KIND_ERROR and i + ERROR_RECORD_BYTES <= n:
            tcodes.append(TCODE_ERROR)
            words.append((body[i + 2] << 16) | (body[i + 3] << 8))
            i += ERROR_RECORD_BYTES
        else:
            break
    return tcodes, words


# --- host decoder ------------------------------------------------------------

@dataclass
class Samples:
    """Decoded records of one batch, in record order (numpy arrays)."""
    index: np.ndarray        # record index since the query started (int64)
    tcode: np.ndarray        # read time after the scheduled time, in tcode units
    status: np.ndarray       # OK or one of the error states
    counts: np.ndarray       # unwrapped position (valid where status == OK)
    lost_messages: int = 0
    # good samples after a gap too long to unwrap across (or a new query):
    # their position may be off by whole turns, so grip restarts there
    breaks: Optional[np.ndarray] = None

    def __post_init__(self):
        if self.breaks is None:
            self.breaks = np.zeros(len(self.index), dtype=bool)

    @property
    def valid(self) -> np.ndarray:
        return self.status == OK

    def error_counts(self) -> Dict[str, int]:
        if not (self.status.any() or self.lost_messages or self.breaks.any()):
            return {}   # the usual batch (OK is 0)
        counts = np.bincount(self.status, minlength=len(STATUS_NAMES))
        out = {STATUS_NAMES[v]: int(counts[v])
               for v in np.flatnonzero(counts[1:]) + 1}
        if self.lost_messages:
            out["lost_messages"] = self.lost_messages
        if self.breaks.any():
            out["discontinuity"] = int(self.breaks.sum())
        return out


def _empty() -> Samples:
    z = np.zeros(0, dtype=np.int64)
    return Samples(z, z.copy(), z.copy(), z.copy())


@dataclass
class Decoder:
    """Turns sensor_bulk_data payloads into unwrapped counts, statefully.

    time_lost: the MCU counted MAX_PENDING - 1 overflow slots in a row, so its
    count of unread timer events may have stopped at MAX_PENDING: its next
    read belongs to a later event than the record index says, and every
    time from there on is off by the events it lost count of. Those samples
    are TIME_LOST (never used) until reset(), after a new query.

    Unwrapping takes the shorter way round between good reads, which is
    only sure while the filament cannot have moved half a turn between
    them. With max_counts_per_record (the most the filament can move per
    record, see max_counts_per_record()), a good read after a gap in which
    it could have is a break (Samples.breaks: used, but grip restarts
    there), and a read that moved further than the filament can in its gap
    is a JUMP (a bad read, e.g. two flipped bits that parity misses). The
    first read after reset() is a break too. None checks nothing.
    """
    bit_offset: int = 1
    max_counts_per_record: Optional[float] = None
    next_index: int = 0
    last_sequence: int = -1
    last_position: int = -1   # 10-bit raw position of the last good frame
    counts: int = 0           # unwrapped position of the last good frame
    time_lost: bool = False
    last_good_index: Optional[int] = None  # record index of the last good frame
    _other: int = field(init=False, default=0)   # the neighbouring offset
    _overflow_run: int = field(init=False, default=0)

    def __post_init__(self):
        if self.bit_offset not in (0, 1):
            raise FlowloopError(f"bit_offset must be 0 or 1, not {self.bit_offset}")
        self._other = 1 - self.bit_offset

    def reset(self) -> None:
        """A new query: the MCU counts records and messages from 0 again.
        The position carries on (the encoder is absolute)."""
        self.next_index, self.last_sequence = 0, -1
        self.time_lost, self._overflow_run = False, 0
        self.last_good_index = None

    def decode(self, messages: Sequence[Tuple[int, bytes]]) -> Samples:
        """Decode (sequence, payload) pairs, in arrival order."""
        starts, tcodes, words, lost = [], [], [], 0
        first_index, contiguous = None, True
        for sequence, payload in messages:
            if self.last_sequence >= 0 and (
                    (sequence - self.last_sequence) & 0xFFFF) != 1:
                lost += 1
            self.last_sequence = sequence
            tcode, word = self._records(payload[HEADER_BYTES:])
            n = len(tcode)
            if not n:
                continue
            first = payload[0] | (payload[1] << 8)
            index = self.next_index + ((first - self.next_index) & 0xFFFF)
            errors = tcode == TCODE_ERROR
            if errors.any():
                # an overflow record stands for several record slots
                overflow = errors & (((word >> 16) & 0xFF) == ERR_OVERFLOW)
                slots = np.where(overflow, np.maximum((word >> 8) & 0xFF, 1), 1)
                tcode, word = np.repeat(tcode, slots), np.repeat(word, slots)
                n = len(tcode)
            if first_index is None:
                first_index = index
            elif index != self.next_index:
                contiguous = False
            starts.append((index, n))
            tcodes.append(tcode)
            words.append(word)
            self.next_index = index + n
        if not tcodes:
            return _empty()
        tcode = np.concatenate(tcodes) if len(tcodes) > 1 else tcodes[0]
        word = np.concatenate(words) if len(words) > 1 else words[0]
        if contiguous:   # the usual batch: one run of record slots
            index = np.arange(first_index, first_index + len(tcode), dtype=np.int64)
        else:
            first = np.array([i for i, _ in starts], dtype=np.int64)
            count = np.array([n for _, n in starts], dtype=np.int64)
            offset = np.cumsum(count) - count
            index = (np.arange(len(tcode), dtype=np.int64)
                     + np.repeat(first - offset, count))
        samples = self._decode_records(index, tcode, word, contiguous)
        samples.lost_messages = lost
        return samples

    def _records(self, body: bytes) -> Tuple[np.ndarray, np.ndarray]:
        """(tcode, 24-bit word) arrays of one message body (parse_records)."""
        if not len(body) % PLAIN_BYTES:
            frames = np.frombuffer(body, dtype=">u2")
            if not (frames < OCF).any():   # the usual message: all plain
                return (np.full(len(frames), PLAIN_TCODE, dtype=np.int64),
                        frames.astype(np.int64) << (8 - self.bit_offset))
        tcode, word = parse_records(body, self.bit_offset)
        return np.array(tcode, dtype=np.int64), np.array(word, dtype=np.int64)

    def _decode_records(self, index: np.ndarray, tcode: np.ndarray,
                        word: np.ndarray, contiguous: bool = False) -> Samples:
        frame = (word >> (8 - self.bit_offset)) & 0xFFFF
        status = _STATUS_OF_FRAME[frame]
        all_good = not status.any()     # OK is 0
        if not all_good:
            bad = status != OK
            other = _STATUS_OF_FRAME[(word >> (8 - self._other)) & 0xFFFF]
            status[bad & (other == OK) & (status != MISSING)] = MISALIGNED
        is_error = tcode == TCODE_ERROR
        if is_error.any():
            all_good = False
            codes = (word[is_error] >> 16) & 0xFF
            status[is_error] = [_MCU_ERRORS.get(int(c), SPI_TIME) for c in codes]
        if not all_good or self._overflow_run or self.time_lost:
            self._mark_time_lost(status)
            all_good = not status.any()
        pos = frame >> POSITION_SHIFT
        if all_good and contiguous:
            counts = self._unwrap_run(index, pos)
            if counts is not None:
                return Samples(index, tcode, status, counts)
        counts = np.zeros(len(index), dtype=np.int64)
        breaks = np.zeros(len(index), dtype=bool)
        good = np.flatnonzero(status == OK)
        if len(good):
            pos = pos[good]
            if self.max_counts_per_record is None:
                self._unwrap(pos, counts, good)
            else:
                self._unwrap_checked(index, pos, counts, good, status, breaks)
        return Samples(index, tcode, status, counts, breaks=breaks)

    def _unwrap_run(self, index: np.ndarray, pos: np.ndarray) -> Optional[np.ndarray]:
        """Unwrapped counts of a run of good reads one record slot apart,
        following the last good read, when every step is plausible; else
        None (the general path sorts it out)."""
        limit = self.max_counts_per_record
        if self.last_position < 0 or self.last_good_index is None:
            return None
        half = POSITIONS // 2
        first_gap = int(index[0]) - self.last_good_index
        if limit is None or first_gap < 1 or first_gap * limit >= half:
            return None
        steps = np.empty_like(pos)
        steps[0] = pos[0] - self.last_position
        np.subtract(pos[1:], pos[:-1], out=steps[1:])
        steps = (steps + half) % POSITIONS - half
        if int(np.abs(steps).max()) > limit + JUMP_MARGIN_COUNTS:
            return None
        counts = self.counts + np.cumsum(steps)
        self.counts = int(counts[-1])
        self.last_position = int(pos[-1])
        self.last_good_index = int(index[-1])
        return counts

    def _unwrap(self, pos, counts, good) -> None:
        prev = np.empty_like(pos)
        prev[0] = pos[0] if self.last_position < 0 else self.last_position
        prev[1:] = pos[:-1]
        step = (pos - prev + POSITIONS // 2) % POSITIONS - POSITIONS // 2
        unwrapped = self.counts + np.cumsum(step)
        counts[good] = unwrapped
        self.counts = int(unwrapped[-1])
        self.last_position = int(pos[-1])
        self.last_good_index = None

    def _unwrap_checked(self, index, pos, counts, good, status, breaks) -> None:
        limit = self.max_counts_per_record
        half = POSITIONS // 2
        if self.last_good_index is not None:
            # the usual batch: every step short and plausible, no long gap
            at = index[good]
            gaps = at - np.concatenate(([self.last_good_index], at[:-1]))
            steps = (pos - np.concatenate(([self.last_position], pos[:-1]))
                     + half) % POSITIONS - half
            if ((gaps * limit < half).all()
                    and (np.abs(steps) <= gaps * limit + JUMP_MARGIN_COUNTS).all()):
                unwrapped = self.counts + np.cumsum(steps)
                counts[good] = unwrapped
                self.counts = int(unwrapped[-1])
                self.last_position = int(pos[-1])
                self.last_good_index = int(index[good[-1]])
                return
        for i, p in zip(good.tolist(), pos.tolist()):
            step = 0
            if self.last_position >= 0:
                step = (p - self.last_position + half) % POSITIONS - half
            if self.last_good_index is None:
                # the first read, or the first after a new query: no gap known
                breaks[i] = self.last_position >= 0
            else:
                gap = int(index[i]) - self.last_good_index
                if gap * limit >= half:
                    breaks[i] = True
                elif abs(step) > gap * limit + JUMP_MARGIN_COUNTS:
                    status[i] = JUMP
                    continue
            self.counts += step
            self.last_position = p
            self.last_good_index = int(index[i])
            counts[i] = self.counts

    def _mark_time_lost(self, status: np.ndarray) -> None:
        start = 0 if self.time_lost else None
        overflow = status == OVERFLOW
        if start is None and (self._overflow_run or overflow.any()):
            run = self._overflow_run
            for i, is_overflow in enumerate(overflow.tolist()):
                run = run + 1 if is_overflow else 0
                if run >= MAX_PENDING - 1:
                    start, self.time_lost = i + 1, True
                    break
            self._overflow_run = run
        if start is not None:
            tail = status[start:]
            tail[tail == OK] = TIME_LOST


def max_counts_per_record(sample_period_s: float, counts_per_mm: float) -> float:
    """The most the filament can move between two consecutive reads, in
    counts (Decoder.max_counts_per_record)."""
    return MAX_FILAMENT_SPEED_MM_S * sample_period_s * counts_per_mm


# --- the SPI read's time budget ---------------------------------------------
# Klipper's software SPI (src/spi_software.c) costs about 270 MCU cycles per
# bit on an atmega2560 whatever spi_speed asks; faster MCUs need fewer.
SOFTWARE_SPI_CYCLES_PER_BIT = 300
# Chip select, the calls around the transfer, timer reads
READ_OVERHEAD_S = 50e-6
# A read may take at most this share of sample_period: the MCU has a printer
# to run too
MAX_READ_SHARE = 0.25


def read_time_s(spi_speed_hz: float, software_spi: bool, mcu_freq_hz: float) -> float:
    """How long one 24-bit read takes on the bus (expected)."""
    bit_s = 1.0 / spi_speed_hz
    if software_spi:
        bit_s = max(bit_s, SOFTWARE_SPI_CYCLES_PER_BIT / mcu_freq_hz)
    return READ_BYTES * 8 * bit_s + READ_OVERHEAD_S


def max_read_ticks(spi_speed_hz: float, software_spi: bool,
                   mcu_freq_hz: float) -> int:
    """config_ems22's max_read_ticks: a read that takes longer was
    interrupted. Twice the expected time: a hardware bus may round its clock
    divider down to half the speed asked."""
    return int(2 * read_time_s(spi_speed_hz, software_spi, mcu_freq_hz)
               * mcu_freq_hz)


def min_sample_period_s(spi_speed_hz: float, software_spi: bool,
                        mcu_freq_hz: float) -> float:
    """The shortest sample_period the bus can serve (see MAX_READ_SHARE)."""
    return read_time_s(spi_speed_hz, software_spi, mcu_freq_hz) / MAX_READ_SHARE


def records_per_message(rest_ticks: int, ticks_per_s: float) -> int:
    """Plain records the MCU batches per message (query_ems22's max_bytes):
    as many as fit, unless the first would then wait MAX_BATCH_AGE_S or
    more. Larger records fill a message sooner, so they wait less."""
    count, age = 1, rest_ticks
    while count < RECORDS_PER_MSG and age < MAX_BATCH_AGE_S * ticks_per_s:
        age += rest_ticks
        count += 1
    return count


def message_bytes(rest_ticks: int, ticks_per_s: float) -> int:
    return HEADER_BYTES + PLAIN_BYTES * records_per_message(rest_ticks,
                                                             ticks_per_s)


def time_shift_for(mcu_freq: float, span_s: float = 0.002) -> int:
    """Smallest shift whose tcode range (0..254) covers span_s of MCU ticks."""
    shift = 0
    while float(TCODE_ERROR << shift) / mcu_freq < span_s:
        shift += 1
    return shift


def sample_clocks(samples: Samples, start_clock: int, rest_ticks: int,
                  time_shift: int) -> np.ndarray:
    """MCU clock of each record's read (scheduled time + tcode).

    The MCU truncates the delay to tcode << time_shift (no rounding: it
    costs flash), so the read lies in the next 1 << time_shift ticks: take
    the middle of that span. A plain record says only that the read started
    within PLAIN_TCODES units (its tcode is PLAIN_TCODE).
    """
    tcode = np.where(samples.tcode == TCODE_ERROR, 0, samples.tcode)
    return (start_clock + samples.index * rest_ticks
            + read_delay_ticks(tcode, time_shift)).astype(np.float64)


def read_delay_ticks(tcode, time_shift: int):
    """Ticks from a record's timer event to its read, as the host takes it
    from the record's tcode: the middle of the tcode's span."""
    centre = (1 << time_shift) / 2.0 if time_shift else 0.0
    return (tcode << time_shift) + centre


def print_times(clocks: np.ndarray, clock_to_print_time) -> np.ndarray:
    """Print time of each MCU clock. clock_to_print_time (klippy's
    mcu.clock_to_print_time) is linear over a batch: two calls, not one each."""
    base = float(clocks[0])
    t0 = clock_to_print_time(base)
    per_clock = (clock_to_print_time(base + 1e6) - t0) / 1e6
    return t0 + (clocks - base) * per_clock


class FaultMonitor:
    """Counts bad samples by kind; `limit` consecutive bad samples make a
    fault, which clears at the next good sample. Transients only count."""

    STUCK_WINDOWS = 2

    def __init__(self, limit: int = DEFAULT_FAULT_SAMPLES):
        if limit < 1:
            raise FlowloopError(f"fault_samples must be at least 1, not {limit}")
        self.limit = limit
        self.errors: Dict[str, int] = {}
        self.fault: Optional[str] = None
        self.episodes = 0
        self._run = 0
        self._stuck = 0

    def update(self, samples: Samples) -> Optional[str]:
        """Account a batch; return the fault if one started in it."""
        for name, count in samples.error_counts().items():
            self.errors[name] = self.errors.get(name, 0) + count
        started = None
        bad = samples.status != OK
        if len(bad) and not bad[-1] and not self._run:
            # the usual batch: only the bad samples between good ones count
            if bad.any():
                runs = np.diff(np.flatnonzero(np.concatenate(([True], ~bad))))
                short = runs.max() <= self.limit
            else:
                short = True
            if short:
                if self.fault is not None and self.fault != "stuck":
                    self.fault = None
                return None
        # split the batch at good samples: each piece extends or ends a run
        edges = [-1, *np.flatnonzero(~bad).tolist(), len(bad)]
        for a, b in zip(edges[:-1], edges[1:]):
            if a >= 0:  # a good sample ends the run and any sample fault
                self._run = 0
                if self.fault is not None and self.fault != "stuck":
                    self.fault = None
            if b - a - 1 <= 0:
                continue
            self._run += b - a - 1
            if self._run >= self.limit and self.fault is None:
                self.fault = STATUS_NAMES[int(samples.status[b - 1])]
                self.episodes += 1
                started = self.fault
        return started

    def note_window(self, reason: str) -> Optional[str]:
        """Account a closed grip window (see grip.GripEstimator)."""
        if reason != STUCK:
            if reason == JUDGED:
                self._stuck = 0
                if self.fault == "stuck":
                    self.fault = None
            return None
        self.errors["stuck"] = self.errors.get("stuck", 0) + 1
        self._stuck += 1
        if self._stuck >= self.STUCK_WINDOWS and self.fault is None:
            self.fault = "stuck"
            self.episodes += 1
            return self.fault
        return None
