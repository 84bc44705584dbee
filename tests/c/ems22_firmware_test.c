// Host run of mcu_sensor/sensor_ems22.c itself (the firmware's own code, with
// the Klipper calls it makes stood in by tests/c/klipper_stubs), driven by a
// script on stdin so that test_ems22_frame.py can decode what it sends with
// flowloop.ems22 and compare it with what really happened:
//
//   n                               the SPI bus config_ems22 gets has no cs
//                                   pin (before c)
//   c MAX_READ_TICKS BIT_OFFSET     config_ems22 (first)
//   q CLOCK REST_TICKS TIME_SHIFT MAX_BYTES
//                                   query_ems22 (REST_TICKS 0 stops)
//   t N                             the timer fires N times
//   r DELAY SPI_TICKS RAW24         the task runs DELAY ticks after the latest
//                                   timer event; its SPI read takes SPI_TICKS
//                                   and returns the 3 bytes RAW24 (hex)
//
// Every sensor_bulk_data message is printed as "data SEQUENCE HEXPAYLOAD".
#include <stdio.h>
#include <string.h>
#include "sensor_ems22.c"

static uint32_t now, last_event;
static uint8_t next_raw[EMS22_READ_BYTES];
static uint32_t spi_ticks;
static struct timer *armed;
static union { struct ems22 e; uint8_t bytes[64]; } oid0;
static int allocated;
static int have_cs_pin = 1;

void *
oid_alloc(uint8_t oid, void *type, uint16_t size)
{
    (void)type;
    if (oid || size > sizeof(oid0))
        shutdown("stub: one small oid only");
    allocated = 1;
    return &oid0;
}

void *
oid_lookup(uint8_t oid, void *type)
{
    (void)type;
    if (oid || !allocated)
        shutdown("stub: unknown oid");
    return &oid0;
}

void *
oid_only(void *type)
{
    (void)type;
    return allocated ? &oid0 : NULL;
}

uint32_t
timer_read_time(void)
{
    return now;
}

void sched_add_timer(struct timer *t) { armed = t; }
void sched_del_timer(struct timer *t) { if (armed == t) armed = NULL; }
void sched_wake_task(struct task_wake *w) { w->wake = 1; }

uint8_t
sched_check_wake(struct task_wake *w)
{
    uint8_t wake = w->wake;
    w->wake = 0;
    return wake;
}

struct spidev_s *spidev_oid_lookup(uint8_t oid) { (void)oid; return NULL; }
int spidev_have_cs_pin(struct spidev_s *spi) { (void)spi; return have_cs_pin; }

void
spidev_transfer(struct spidev_s *spi, uint8_t receive_data
                , uint8_t data_len, uint8_t *data)
{
    (void)spi;
    if (!receive_data || data_len != EMS22_READ_BYTES)
        shutdown("stub: unexpected spi transfer");
    memcpy(data, next_raw, data_len);
    now += spi_ticks;
}

// As Klipper's src/sensor_bulk.c does it
void
sensor_bulk_reset(struct sensor_bulk *sb)
{
    sb->sequence = 0;
    sb->possible_overflows = 0;
    sb->data_count = 0;
}

void
sensor_bulk_report(struct sensor_bulk *sb, uint8_t oid)
{
    printf("data %u ", sb->sequence);
    for (int i = 0; i < sb->data_count; i++)
        printf("%02x", sb->data[i]);
    printf("\n");
    (void)oid;
    sb->data_count = 0;
    sb->sequence++;
}

int
main(void)
{
    char op;
    while (scanf(" %c", &op) == 1) {
        unsigned long a, b, c, d;
        if (op == 'n') {
            have_cs_pin = 0;
        } else if (op == 'c' && scanf("%lu %lu", &a, &b) == 2) {
            uint32_t args[4] = { 0, 0, a, b };
            command_config_ems22(args);
        } else if (op == 'q'
                   && scanf("%lu %lu %lu %lu", &a, &b, &c, &d) == 4) {
            uint32_t q[5] = { 0, a, b, c, d };
            command_query_ems22(q);
        } else if (op == 't' && scanf("%lu", &a) == 1) {
            while (a-- && armed) {
                now = last_event = armed->waketime;
                armed->func(armed);
            }
        } else if (op == 'r' && scanf("%lu %lu %lx", &a, &b, &c) == 3) {
            now = last_event + a;
            spi_ticks = b;
            next_raw[0] = c >> 16;
            next_raw[1] = c >> 8;
            next_raw[2] = c;
            ems22_task();
        } else {
            printf("bad script at '%c'\n", op);
            return 1;
        }
    }
    return 0;
}
