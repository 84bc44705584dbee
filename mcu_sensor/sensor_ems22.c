// Polling a Bourns EMS22A absolute encoder (flowloop's filament flow sensor)
//
// A timer marks a poll pending and wakes the task; the task does the SPI
// read, so no SPI traffic ever runs in interrupt context. Every timer event
// produces exactly one record (a sample or an error), and every message
// carries the index of its first record, so the host rebuilds each sample's
// time exactly even if a message is lost.
//
// This file may be distributed under the terms of the GNU GPLv3 license.

#include "basecmd.h" // oid_alloc
#include "board/irq.h" // irq_disable
#include "board/misc.h" // timer_read_time
#include "command.h" // DECL_COMMAND
#include "ems22_frame.h" // EMS22_RECORD_BYTES
#include "sched.h" // DECL_TASK
#include "sensor_bulk.h" // sensor_bulk_report
#include "spicmds.h" // spidev_transfer

struct ems22 {
    struct timer timer;
    // A read that takes longer was interrupted: the host derives the limit
    // from the bus (speed, software or hardware SPI)
    uint32_t rest_ticks, max_read_ticks;
    struct spidev_s *spi;
    uint16_t next_index;
    // Timer events not yet read: more than one means the task fell behind
    uint8_t pending, time_shift, max_bytes, oid, bit_offset;
    struct sensor_bulk sb;
};

static struct task_wake ems22_wake;
// The sensor whose timer woke the task, so the task need not walk every oid
// (about 170 cycles a sample on an atmega2560); ems22_several when more
// than one sensor has woken it since it last ran.
static struct ems22 *ems22_woken;
static uint8_t ems22_several;

// Timer: only count the poll as pending (up to 255) and wake the task
static uint_fast8_t
ems22_event(struct timer *timer)
{
    struct ems22 *e = container_of(timer, struct ems22, timer);
    if (e->pending < 255)
        e->pending++;
    if (!ems22_woken)
        ems22_woken = e;
    else if (ems22_woken != e)
        ems22_several = 1;
    sched_wake_task(&ems22_wake);
    e->timer.waketime += e->rest_ticks;
    return SF_RESCHEDULE;
}

void
command_config_ems22(uint32_t *args)
{
    struct ems22 *e = oid_alloc(args[0], command_config_ems22, sizeof(*e));
    e->timer.func = ems22_event;
    e->oid = args[0];
    e->spi = spidev_oid_lookup(args[1]);
    if (!spidev_have_cs_pin(e->spi))
        shutdown("ems22 requires cs pin");
    e->max_read_ticks = args[2];
    e->bit_offset = args[3];
}
DECL_COMMAND(command_config_ems22,
             "config_ems22 oid=%c spi_oid=%c max_read_ticks=%u bit_offset=%c");

// Append one record of len bytes; a new message starts with the index of
// its first record. The host's max_bytes (clamped) leaves room for any
// record, so a message is only ever sent once it holds max_bytes.
static void
ems22_add(struct ems22 *e, const uint8_t *rec, uint_fast8_t len)
{
    struct sensor_bulk *sb = &e->sb;
    if (!sb->data_count) {
        sb->data[0] = e->next_index;
        sb->data[1] = e->next_index >> 8;
        sb->data_count = EMS22_HEADER_BYTES;
    }
    uint8_t *d = &sb->data[sb->data_count];
    sb->data_count += len;
    while (len--)
        *d++ = *rec++;
    e->next_index++;
    // Send once the message holds max_bytes (the host sizes max_bytes so
    // that a message's first record never waits long: query_ems22)
    if (sb->data_count >= e->max_bytes) {
        sensor_bulk_report(sb, e->oid);
        // sensor_bulk_report empties sb too, but without this line
        // avr-gcc makes the firmware 8 bytes larger
        sb->data_count = 0;
    }
}

// One SPI read of 24 clocks (the chip takes no command: DI idles).
// Returns 0 when the transfer took too long to be trusted.
static int
ems22_read(struct ems22 *e, uint8_t *raw, uint32_t *mtime)
{
    raw[0] = raw[1] = raw[2] = 0;
    uint32_t mtime1 = timer_read_time();
    spidev_transfer(e->spi, 1, EMS22_READ_BYTES, raw);
    uint32_t mtime2 = timer_read_time();
    *mtime = mtime1;
    return mtime2 - mtime1 <= e->max_read_ticks;
}

// A good frame read on time is sent as a plain 2-byte record; any other
// read goes out whole with its time code, and the host judges it (which
// neighbouring bits tell a misaligned SPI mode from a fault). Every path
// ends in the one ems22_add call (flash is scarce on small MCUs).
static void
ems22_sample(struct ems22 *e, uint32_t stime)
{
    // 0, kind, tcode or error code, then the raw read or the error count;
    // a plain record is the last two bytes
    uint8_t rec[EMS22_READ_RECORD_BYTES];
    uint8_t *raw = &rec[3], *start = rec;
    uint_fast8_t len = EMS22_ERROR_RECORD_BYTES;
    uint32_t mtime;
    rec[0] = 0;
    rec[1] = EMS22_KIND_ERROR;
    rec[2] = EMS22_ERR_SPI_TIME;
    if (ems22_read(e, raw, &mtime)) {
        uint32_t delay = mtime - stime;
        uint16_t frame = ems22_frame_at(raw, e->bit_offset);
        uint32_t tdiff = delay >> e->time_shift;
        if (tdiff < EMS22_PLAIN_TCODES && ems22_frame_good(frame)) {
            rec[4] = frame >> 8;
            rec[5] = frame;
            start = &rec[4];
            len = EMS22_PLAIN_BYTES;
        } else if (tdiff < EMS22_TCODE_ERROR) {
            rec[1] = EMS22_KIND_READ;
            rec[2] = tdiff;
            len = EMS22_READ_RECORD_BYTES;
        } else {
            rec[2] = EMS22_ERR_SCHEDULE;
            raw[0] = 0;
        }
    } else {
        raw[0] = 0;
    }
    ems22_add(e, start, len);
}

void
command_query_ems22(uint32_t *args)
{
    uint8_t oid = args[0];
    struct ems22 *e = oid_lookup(oid, command_config_ems22);
    sched_del_timer(&e->timer);
    e->pending = 0;
    if (!args[2])
        // End measurements
        return;
    e->timer.waketime = args[1];
    e->rest_ticks = args[2];
    e->time_shift = args[3];
    // Message size: the host keeps a batch's first record from waiting long
    uint8_t max_bytes = args[4];
    if (max_bytes > EMS22_MAX_BATCH_BYTES)
        max_bytes = EMS22_MAX_BATCH_BYTES;
    e->max_bytes = max_bytes;
    e->next_index = 0;
    sensor_bulk_reset(&e->sb);
    sched_add_timer(&e->timer);
}
DECL_COMMAND(command_query_ems22,
             "query_ems22 oid=%c clock=%u rest_ticks=%u time_shift=%c"
             " max_bytes=%c");

// Read one sensor's pending poll
static void
ems22_poll(struct ems22 *e)
{
    irq_disable();
    uint32_t stime = e->timer.waketime;
    uint_fast8_t pending = e->pending;
    e->pending = 0;
    irq_enable();
    if (!pending)
        return;   // stopped (query_ems22) since its timer woke the task
    // Missed events take the earlier record slots, in one record that
    // counts them (one message, not one per event, after a stall); the
    // read now belongs to the latest event (waketime points at the next)
    uint_fast8_t overflow = pending - 1;
    if (overflow) {
        uint8_t rec[EMS22_ERROR_RECORD_BYTES] = {
            0, EMS22_KIND_ERROR, EMS22_ERR_OVERFLOW, overflow };
        ems22_add(e, rec, sizeof(rec));
        e->next_index += overflow - 1;
    }
    ems22_sample(e, stime - e->rest_ticks);
}

void
ems22_task(void)
{
    if (!sched_check_wake(&ems22_wake))
        return;
    irq_disable();
    struct ems22 *woken = ems22_woken;
    uint8_t several = ems22_several;
    ems22_woken = NULL;
    ems22_several = 0;
    irq_enable();
    if (!several) {
        if (woken)
            ems22_poll(woken);
        return;
    }
    uint8_t oid;
    struct ems22 *e;
    foreach_oid(oid, e, command_config_ems22) {
        ems22_poll(e);
    }
    (void)oid;   // each sensor keeps its own
}
DECL_TASK(ems22_task);

void
ems22_shutdown(void)
{
    // a config_reset (which needs a shutdown first) frees every oid
    ems22_woken = NULL;
    ems22_several = 0;
}
DECL_SHUTDOWN(ems22_shutdown);
