// Bourns EMS22A frame checks and the flowloop bulk record layout.
//
// Pure header: no Klipper includes, so the same code is compiled into the
// MCU firmware (record layout) and into the host test program (tests/c). The Python side
// (flowloop/ems22.py) mirrors these constants; tests/data/ems22_vectors.json
// holds the vectors both are checked against.
//
// This file may be distributed under the terms of the GNU GPLv3 license.
#ifndef __EMS22_FRAME_H
#define __EMS22_FRAME_H

#include <stdint.h> // uint16_t

// One read clocks 24 bits: the 16-bit frame plus spare clocks (the chip then
// shifts out DI), so a frame that arrives one bit late is still whole.
#define EMS22_READ_BYTES 3
// sensor_bulk_data payload: 2-byte index of the first record (low 16 bits of
// the timer event counter), then one record per timer event, of three kinds:
//  - plain, 2 bytes: the 16-bit frame (big-endian) of a read that passed
//    ems22_frame_good() and started less than EMS22_PLAIN_TCODES tcode
//    units after its timer event (the usual record);
//  - EMS22_KIND_READ, 6 bytes: 0x00, kind, tcode, the raw 24-bit read: a read
//    that is not plain (a bad frame, or a late one), so the host judges it
//    (a misaligned SPI mode shows in the neighbouring bits) and times it;
//  - EMS22_KIND_ERROR, 4 bytes: 0x00, kind, error code, count.
// A first byte 0x00 with a second below EMS22_OCF never starts a plain
// record: every good frame has OCF set in its low byte.
#define EMS22_HEADER_BYTES 2
#define EMS22_PLAIN_BYTES 2
#define EMS22_READ_RECORD_BYTES (2 + 1 + EMS22_READ_BYTES)
#define EMS22_ERROR_RECORD_BYTES 4
#define EMS22_KIND_READ 1
#define EMS22_KIND_ERROR 2
// Klipper's sensor_bulk buffer (src/sensor_bulk.h): a message holds at most
#define EMS22_MAX_MSG_BYTES 51
// A message is sent once it holds this many bytes or fewer (the host's
// max_bytes, clamped here), so that any record still fits before it is
#define EMS22_MAX_BATCH_BYTES (EMS22_MAX_MSG_BYTES - EMS22_READ_RECORD_BYTES + 1)
// Time code: read time - scheduled time, >> time_shift, below
// EMS22_TCODE_ERROR (a read later than that is an EMS22_ERR_SCHEDULE).
#define EMS22_TCODE_ERROR 0xff
// A plain record's read started within this many tcode units (the host
// takes the middle): about 0.1 ms on any MCU, 8 us units at 16 MHz
#define EMS22_PLAIN_TCODES 16
enum {
    EMS22_ERR_OVERFLOW = 1,   // timer fired again before the task read; the
                              // next byte counts the events (record slots)
    EMS22_ERR_SCHEDULE = 2,   // read too late to encode its time
    EMS22_ERR_SPI_TIME = 3,   // the SPI transfer took too long
};

// Frame bits (bit 15 first on the wire): D9..D0, OCF, COF, LIN, MagINC,
// MagDEC, even parity over bits 15..1.
#define EMS22_POSITION_SHIFT 6
#define EMS22_OCF     (1 << 5)
#define EMS22_COF     (1 << 4)
#define EMS22_LIN     (1 << 3)
#define EMS22_MAGINC  (1 << 2)
#define EMS22_MAGDEC  (1 << 1)

enum {
    EMS22_OK = 0,
    EMS22_MISSING,      // all 0s or all 1s: no chip driving DO
    EMS22_PARITY,
    EMS22_NOT_READY,    // OCF still 0
    EMS22_CORDIC,       // COF: CORDIC overflow
    EMS22_LINEARITY,    // LIN alarm
    EMS22_MAGNET,       // MagINC and MagDEC both set: magnet out of range
};

// 1 when the 16 bits hold an odd number of ones (a parity error).
static inline uint_fast8_t
ems22_parity_odd(uint16_t frame)
{
    uint_fast8_t v = (frame >> 8) ^ (frame & 0xff);
    v ^= v >> 4;
    v ^= v >> 2;
    v ^= v >> 1;
    return v & 1;
}

// The 16-bit frame whose first bit is bit 'offset' (0 or 1) of a 24-bit
// read (every SPI mode puts it at one of the two)
static inline uint16_t
ems22_frame_at(const uint8_t *raw, uint_fast8_t offset)
{
    uint16_t frame = ((uint16_t)raw[0] << 8) | raw[1];
    if (offset)
        frame = (frame << 1) | (raw[2] >> 7);
    return frame;
}

static inline uint_fast8_t
ems22_frame_check(uint16_t frame)
{
    if (frame == 0x0000 || frame == 0xffff)
        return EMS22_MISSING;
    if (ems22_parity_odd(frame))
        return EMS22_PARITY;
    if (!(frame & EMS22_OCF))
        return EMS22_NOT_READY;
    if (frame & EMS22_COF)
        return EMS22_CORDIC;
    if (frame & EMS22_LIN)
        return EMS22_LINEARITY;
    if ((frame & (EMS22_MAGINC | EMS22_MAGDEC))
        == (EMS22_MAGINC | EMS22_MAGDEC))
        return EMS22_MAGNET;
    return EMS22_OK;
}

// ems22_frame_check(frame) == EMS22_OK, in fewer instructions (the
// firmware's test for a plain record): all 1s fails on COF, all 0s on OCF
static inline uint_fast8_t
ems22_frame_good(uint16_t frame)
{
    uint8_t low = frame;
    return (low & (EMS22_OCF | EMS22_COF | EMS22_LIN)) == EMS22_OCF
        && (low & (EMS22_MAGINC | EMS22_MAGDEC)) != (EMS22_MAGINC | EMS22_MAGDEC)
        && !ems22_parity_odd(frame);
}

static inline uint16_t
ems22_position(uint16_t frame)
{
    return frame >> EMS22_POSITION_SHIFT;
}

// A read that holds a good frame at bit offset 0 or 1, whatever the SPI
// mode: for a good frame only its own offset passes (read bit 12 is its
// COF=0 at offset 0 but would have to be OCF=1 at offset 1). The firmware
// sends every read as is (the host knows the mode); tests/c uses this.
static inline uint_fast8_t
ems22_read_plausible(const uint8_t *raw)
{
    uint_fast8_t off;
    for (off = 0; off < 2; off++) {
        uint16_t frame = ems22_frame_at(raw, off);
        if (frame != 0xffff && !ems22_parity_odd(frame)
            && (frame & (EMS22_OCF | EMS22_COF)) == EMS22_OCF)
            return 1;
    }
    return 0;
}

#endif // ems22_frame.h
