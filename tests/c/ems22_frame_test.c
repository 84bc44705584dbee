// Host test of mcu_sensor/ems22_frame.h.
//
// 1. Reads vectors (raw24 offset status position per line, made from
//    tests/data/ems22_vectors.json by test_ems22_frame.py) on stdin and
//    checks the header's decode of each.
// 2. Exhaustively checks every position and status-flag combination against
//    an edge-by-edge model of the chip's DO line in all four SPI modes.
// 3. Checks ems22_frame_good() against ems22_frame_check() on every frame.
#include <stdio.h>
#include <stdint.h>
#include "ems22_frame.h"

static int failures;

static uint16_t
make_frame(uint16_t position, uint8_t flags)
{
    uint16_t frame = (position << EMS22_POSITION_SHIFT) | ((flags & 0x1f) << 1);
    return frame | ems22_parity_odd(frame);
}

// The chip drives a new bit at each rising CLK edge (D9 first, then DI);
// the master samples on the leading (CPHA=0) or trailing (CPHA=1) edge and
// reads the level from before a change at that same edge.
static void
model_read(uint16_t frame, int mode, int idle_do, int di, uint8_t *raw)
{
    int cpol = mode >> 1, cpha = mode & 1, clk = cpol, rises = 0, do_level = idle_do;
    int nbits = 0, bit, edge;
    raw[0] = raw[1] = raw[2] = 0;
    for (bit = 0; bit < 24; bit++) {
        for (edge = 0; edge < 2; edge++) {
            clk ^= 1;
            if (edge == cpha) {
                raw[nbits / 8] |= do_level << (7 - nbits % 8);
                nbits++;
            }
            if (clk) {
                do_level = rises < 16 ? (frame >> (15 - rises)) & 1 : di;
                rises++;
            }
        }
    }
}

static void
check_vectors(void)
{
    unsigned long raw24;
    unsigned offset, status, position;
    int count = 0;
    while (scanf("%lx %u %u %u", &raw24, &offset, &status, &position) == 4) {
        uint8_t raw[3] = { raw24 >> 16, raw24 >> 8, raw24 };
        uint16_t frame = ems22_frame_at(raw, offset);
        unsigned got = ems22_frame_check(frame);
        if (got != status || (got == EMS22_OK && ems22_position(frame) != position)) {
            printf("vector %06lx offset %u: status %u position %u,"
                   " expected %u %u\n", raw24, offset, got,
                   ems22_position(frame), status, position);
            failures++;
        }
        count++;
    }
    printf("vectors: %d checked\n", count);
    if (count < 10) {
        printf("too few vectors\n");
        failures++;
    }
}

static void
check_model(void)
{
    long checked = 0;
    for (int mode = 0; mode < 4; mode++) {
        // Modes sampling on falling edges see the frame at offset 0 only
        // when the first edge is rising (mode 1); all others one bit late.
        unsigned offset = mode == 1 ? 0 : 1;
        for (unsigned pos = 0; pos < 1024; pos++) {
            for (unsigned flags = 0; flags < 32; flags++) {
                for (int idle = 0; idle < 2; idle++) {
                    uint16_t frame = make_frame(pos, flags);
                    uint8_t raw[3];
                    model_read(frame, mode, idle, 0, raw);
                    uint16_t got = ems22_frame_at(raw, offset);
                    unsigned expect_ok = (flags & 0x1f) == 0x10
                        || (flags & 0x1f) == 0x11 || (flags & 0x1f) == 0x12;
                    // flags bit4 = OCF, bit3 COF, bit2 LIN, bit1 MagINC, bit0 MagDEC
                    unsigned status = ems22_frame_check(got);
                    if (got != frame || (status == EMS22_OK) != expect_ok
                        || (status == EMS22_OK && ems22_position(got) != pos)
                        || (((flags & 0x18) == 0x10) && !ems22_read_plausible(raw))) {
                        if (failures++ < 10)
                            printf("mode %d pos %u flags %02x: frame %04x got %04x"
                                   " status %u\n", mode, pos, flags, frame, got,
                                   status);
                    }
                    // Read at the wrong offset: never silently accepted
                    uint16_t wrong = ems22_frame_at(raw, 1 - offset);
                    if (status == EMS22_OK && ems22_frame_check(wrong) == EMS22_OK) {
                        if (failures++ < 10)
                            printf("mode %d pos %u: misaligned frame %04x passed\n",
                                   mode, pos, wrong);
                    }
                    checked++;
                }
            }
        }
    }
    printf("model: %ld reads checked\n", checked);
}

// The firmware's short test for a plain record agrees with the full check
static void
check_good(void)
{
    long good = 0;
    for (uint32_t f = 0; f < 0x10000; f++) {
        unsigned expect = ems22_frame_check(f) == EMS22_OK;
        if (ems22_frame_good(f) != expect) {
            if (failures++ < 10)
                printf("frame %04x: ems22_frame_good %u, check says %u\n",
                       (unsigned)f, (unsigned)ems22_frame_good(f), expect);
        }
        good += expect;
    }
    printf("good: %ld of 65536 frames\n", good);
}

int
main(void)
{
    check_vectors();
    check_model();
    check_good();
    printf("%s\n", failures ? "FAIL" : "OK");
    return failures ? 1 : 0;
}
