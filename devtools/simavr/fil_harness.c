// Firmware in the loop: Klipper's atmega2560 firmware on simavr, paced to the
// wall clock, with USART0 on a pty and flowloop's sensor, filament and hotend
// attached at the pins (devtools/simavr/harness.py builds and starts it).
//
// - EMS22: the chip's frame leaves on DO bit by bit, the next bit on each
//   rising CLK edge (valid 375 ns later), as the datasheet gives it. On
//   hardware SPI the clock edges come from the SPI mode the firmware wrote
//   into SPCR; on software SPI from the SCK pin itself. Nothing here knows
//   which mode flowloop's config asked for.
// - Filament: the shaft follows the extruder's step/dir pins through a grip
//   the control socket sets (a step or a ramp in simulated time).
// - Faults on command, the heater pin's duty, the thermistor's ADC input.
// - Control: one line per command on a Unix socket, one line back.
//
// This file may be distributed under the terms of the GNU GPLv3 license.

#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_irq.h"
#include "sim_cycle_timers.h"
#include "avr_ioport.h"
#include "avr_uart.h"
#include "avr_spi.h"
#include "avr_adc.h"

#define SPCR_ADDR 0x4c  // atmega2560 SPCR in data space (I/O 0x2c)
#define SPSR_ADDR 0x4d
#define SPSR_SPIF 0x80
#define SPCR_DORD 0x20
#define SPCR_CPOL 0x08
#define SPCR_CPHA 0x04
#define POSITIONS 1024
// DO is valid 375 ns after the rising CLK edge
#define DO_DELAY_NS 375

static avr_t *avr;
static volatile sig_atomic_t stop_requested;
static uint32_t freq_hz = 16000000;

struct pin { char port; int bit; };

static int
parse_pin(const char *s, struct pin *p)
{
    if (strlen(s) != 3 || s[0] != 'P' || s[1] < 'A' || s[1] > 'L'
        || s[2] < '0' || s[2] > '7')
        return -1;
    p->port = s[1];
    p->bit = s[2] - '0';
    return 0;
}

static avr_irq_t *
pin_irq(struct pin p)
{
    return avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(p.port), p.bit);
}

static double
sim_seconds(void)
{
    return (double)avr->cycle / freq_hz;
}

// --- the filament ------------------------------------------------------------
static struct {
    double mm_per_step, counts_per_mm;
    double mm;              // filament through the sensor
    long steps;             // extruder steps, signed by the dir pin
    int dir_level, dir_invert, both_edges;
    // grip: from grip0 at t0 to grip1 at t1 (a step when t1 <= t0)
    double grip0, grip1, t0, t1;
    long offset_counts;     // shaft angle at the start
} fil = { .grip0 = 1.0, .grip1 = 1.0, .offset_counts = 300 };

static double
grip_now(void)
{
    double t = sim_seconds();
    if (t >= fil.t1 || fil.t1 <= fil.t0)
        return fil.grip1;
    if (t <= fil.t0)
        return fil.grip0;
    return fil.grip0 + (fil.grip1 - fil.grip0) * (t - fil.t0) / (fil.t1 - fil.t0);
}

static long
shaft_counts(void)
{
    return lround(fil.mm * fil.counts_per_mm) + fil.offset_counts;
}

static void
on_step(avr_irq_t *irq, uint32_t value, void *param)
{
    if (!fil.both_edges && !value)
        return;
    if (fil.both_edges && value == irq->value)
        return;
    int forward = fil.dir_level ^ fil.dir_invert;
    fil.steps += forward ? 1 : -1;
    fil.mm += (forward ? 1 : -1) * fil.mm_per_step * grip_now();
}

static void
on_dir(avr_irq_t *irq, uint32_t value, void *param)
{
    fil.dir_level = value ? 1 : 0;
}

// --- the EMS22 -----------------------------------------------------------------
enum { F_NONE, F_PARITY, F_NOT_READY, F_CORDIC, F_LINEARITY, F_MAGNET,
       F_MISO_HIGH, F_MISO_LOW, F_ABSENT };
static const char *fault_names[] = {
    "none", "parity", "not_ready", "cordic", "linearity", "magnet",
    "miso_high", "miso_low", "absent" };

static struct {
    int software;           // 1: watch SCK and drive MISO pins
    struct pin cs, sck, miso;
    avr_irq_t *miso_irq;
    int cs_low, sck_level, rises, do_level;
    uint16_t frame;
    int fault;
    unsigned long frames, bytes;
    // A stall: the next hardware SPI byte completes this many cycles late,
    // holding the firmware's sensor task in its transfer (a bus held up)
    avr_cycle_count_t stall_cycles;
} chip = { .cs_low = 0, .do_level = 1 };

static int
parity_odd(uint16_t v)
{
    return __builtin_parity(v);
}

static uint16_t
make_frame(long counts)
{
    uint16_t pos = ((counts % POSITIONS) + POSITIONS) % POSITIONS;
    uint16_t status = 1 << 5;  // OCF
    switch (chip.fault) {
    case F_NOT_READY: status = 0; break;
    case F_CORDIC: status |= 1 << 4; break;
    case F_LINEARITY: status |= 1 << 3; break;
    case F_MAGNET: status |= (1 << 2) | (1 << 1); break;
    }
    uint16_t frame = (pos << 6) | status;
    frame |= parity_odd(frame);  // even parity over bits 15..1
    if (chip.fault == F_PARITY)
        frame ^= 1;
    return frame;
}

// The level on MISO as the master sees it
static int
miso_level(void)
{
    switch (chip.fault) {
    case F_MISO_HIGH: return 1;
    case F_MISO_LOW: return 0;
    case F_ABSENT: return 0;  // hardware SPI: MISO has no pull-up there
    }
    return chip.cs_low ? chip.do_level : 1;
}

// Software SPI: a driven MISO overrides the pin's pull-up (simavr applies a
// pull-up at every write of the port unless an external level is set); an
// absent chip leaves it floating, to the pull-up if the firmware set one.
static void
drive_miso(void)
{
    if (!chip.software)
        return;
    int driven = chip.fault != F_ABSENT;
    int level = miso_level();
    avr_ioport_external_t ext = {
        .name = chip.miso.port, .mask = driven ? 1 << chip.miso.bit : 0,
        .value = driven && level ? 1 << chip.miso.bit : 0 };
    avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL(chip.miso.port), &ext);
    if (driven)
        avr_raise_irq(chip.miso_irq, level);
}

static void
chip_rise(void)
{
    chip.do_level = chip.rises < 16 ? (chip.frame >> (15 - chip.rises)) & 1 : 0;
    chip.rises++;
}

static void
on_cs(avr_irq_t *irq, uint32_t value, void *param)
{
    int low = !value;
    if (low == chip.cs_low)
        return;
    chip.cs_low = low;
    if (low) {  // CSn falling latches the frame; DO idles high until a clock
        chip.frame = make_frame(shaft_counts());
        chip.rises = 0;
        chip.do_level = 1;
        chip.frames++;
    }
    drive_miso();
}

// The SPI is named '0' in some simavr cores and 0 in others (the atmega2560's)
static avr_irq_t *
spi_irq(int which)
{
    avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_SPI_GETIRQ('0'), which);
    return irq ? irq : avr_io_getirq(avr, AVR_IOCTL_SPI_GETIRQ(0), which);
}

static avr_cycle_count_t
spi_stall_end(avr_t *a, avr_cycle_count_t when, void *param)
{
    avr->data[SPSR_ADDR] |= SPSR_SPIF;
    return 0;
}

// Hardware SPI: simavr hands over each byte the AVR sent when it is done; the
// byte the chip returns follows the clock edges of the mode in SPCR.
static void
on_spi_byte(avr_irq_t *irq, uint32_t value, void *param)
{
    uint8_t spcr = avr->data[SPCR_ADDR];
    int cpol = !!(spcr & SPCR_CPOL), cpha = !!(spcr & SPCR_CPHA);
    int clk = cpol;
    uint8_t in = 0;
    chip.bytes++;
    for (int i = 0; i < 8; i++) {
        for (int edge = 0; edge < 2; edge++) {  // leading, trailing
            clk ^= 1;
            if (edge == cpha)  // sampled before DO changes on this edge
                in = (in << 1) | miso_level();
            if (clk && chip.cs_low && chip.fault != F_ABSENT)
                chip_rise();
        }
    }
    if (spcr & SPCR_DORD) {  // LSB first: the first bit sampled is bit 0
        uint8_t r = 0;
        for (int i = 0; i < 8; i++)
            r |= ((in >> i) & 1) << (7 - i);
        in = r;
    }
    avr_raise_irq(spi_irq(SPI_IRQ_INPUT), in);
    if (chip.stall_cycles) {
        avr->data[SPSR_ADDR] &= ~SPSR_SPIF;
        avr_cycle_timer_register(avr, chip.stall_cycles, spi_stall_end, NULL);
        chip.stall_cycles = 0;
    }
}

static avr_cycle_count_t
do_valid(avr_t *a, avr_cycle_count_t when, void *param)
{
    chip_rise();
    drive_miso();
    return 0;
}

// Software SPI: the chip sees the SCK pin itself
static void
on_sck(avr_irq_t *irq, uint32_t value, void *param)
{
    int level = value ? 1 : 0;
    if (level == chip.sck_level)
        return;
    chip.sck_level = level;
    if (level && chip.cs_low && chip.fault != F_ABSENT) {
        chip.bytes++;
        avr_cycle_count_t delay = (uint64_t)DO_DELAY_NS * freq_hz / 1000000000ull;
        avr_cycle_timer_register(avr, delay ? delay : 1, do_valid, NULL);
    }
}

// --- the hotend: heater pin duty in, thermistor voltage out -------------------
static struct {
    struct pin heater;
    int enabled, level, adc_channel;
    avr_cycle_count_t since, on_cycles, window_start;
} hot = { .adc_channel = -1 };

static void
on_heater(avr_irq_t *irq, uint32_t value, void *param)
{
    int level = value ? 1 : 0;
    if (level == hot.level)
        return;
    if (hot.level)
        hot.on_cycles += avr->cycle - hot.since;
    hot.since = avr->cycle;
    hot.level = level;
}

// Duty since the last call (the host's hotend model integrates it)
static double
heater_duty(void)
{
    avr_cycle_count_t now = avr->cycle, on = hot.on_cycles;
    if (hot.level)
        on += now - hot.since;
    double span = now - hot.window_start;
    hot.on_cycles = 0;
    hot.since = hot.window_start = now;
    return span > 0 ? on / span : 0.;
}

static void
set_adc_mv(uint32_t mv)
{
    if (hot.adc_channel >= 0)
        avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ,
                                    ADC_IRQ_ADC0 + hot.adc_channel), mv);
}

// --- USART0 <-> pty ----------------------------------------------------------
// A byte from the host reaches the UART at exactly INPUT_DELAY_S of simulated
// time after the wall time it was read from the pty. The simulation runs at
// most one pacing step (0.5 ms) ahead of the wall clock, so that moment is
// still to come; when the simulation has fallen behind (this process woke
// late: up to several ms at times on a VM) it catches up before the MCU sees
// the byte, as a real MCU's crystal would have. Fed at once instead, a klippy
// `get_clock` answered while the simulation lagged read a clock that much
// early, and the clock samples klippy estimates the MCU's frequency from
// scattered by the lag instead of by the pty's latency.
#define INPUT_DELAY_S 0.0006

static struct {
    int master, slave;
    int xon;
    uint8_t in[4096];
    avr_cycle_count_t in_release[4096];   // the cycle each byte is due
    int in_head, in_tail;
    int release_pending;
    unsigned long to_host, from_host, dropped;
} serial = { .master = -1, .slave = -1 };

static avr_cycle_count_t release_input(avr_t *a, avr_cycle_count_t when, void *param);

static void
push_input(void)
{
    avr_irq_t *dst = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    while (serial.xon && serial.in_head != serial.in_tail
           && serial.in_release[serial.in_tail] <= avr->cycle) {
        uint8_t b = serial.in[serial.in_tail];
        serial.in_tail = (serial.in_tail + 1) % sizeof(serial.in);
        avr_raise_irq(dst, b);
    }
    // the next byte's moment (a byte due but held by xoff waits for on_xon)
    if (!serial.release_pending && serial.in_head != serial.in_tail
        && serial.in_release[serial.in_tail] > avr->cycle) {
        serial.release_pending = 1;
        avr_cycle_timer_register(avr, serial.in_release[serial.in_tail] - avr->cycle,
                                 release_input, NULL);
    }
}

static avr_cycle_count_t
release_input(avr_t *a, avr_cycle_count_t when, void *param)
{
    serial.release_pending = 0;
    push_input();
    return 0;
}

static void
on_uart_out(avr_irq_t *irq, uint32_t value, void *param)
{
    uint8_t b = value;
    serial.to_host++;
    if (write(serial.master, &b, 1) != 1)
        serial.dropped++;
}

static void
on_xon(avr_irq_t *irq, uint32_t value, void *param)
{
    serial.xon = 1;
    push_input();
}

static void
on_xoff(avr_irq_t *irq, uint32_t value, void *param)
{
    serial.xon = 0;
}

static double wall_seconds(void);

static void
read_pty(void)
{
    for (;;) {
        int space = (serial.in_tail - serial.in_head - 1 + (int)sizeof(serial.in))
            % (int)sizeof(serial.in);
        if (!space)
            break;
        uint8_t buf[256];
        int n = read(serial.master, buf, space < 256 ? space : 256);
        if (n <= 0)
            break;
        avr_cycle_count_t due = (avr_cycle_count_t)(
            (wall_seconds() + INPUT_DELAY_S) * freq_hz);
        for (int i = 0; i < n; i++) {
            serial.in[serial.in_head] = buf[i];
            serial.in_release[serial.in_head] = due;
            serial.in_head = (serial.in_head + 1) % sizeof(serial.in);
        }
        serial.from_host += n;
    }
    push_input();
}

static int
open_pty(const char *link_path)
{
    serial.master = posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK);
    if (serial.master < 0 || grantpt(serial.master) || unlockpt(serial.master))
        return -1;
    const char *name = ptsname(serial.master);
    // Held open: without a reader the master sees a hangup on every poll,
    // and raw: the line discipline must not echo the MCU's bytes back.
    serial.slave = open(name, O_RDWR | O_NOCTTY);
    if (serial.slave < 0)
        return -1;
    struct termios t;
    tcgetattr(serial.slave, &t);
    cfmakeraw(&t);
    tcsetattr(serial.slave, TCSANOW, &t);
    tcgetattr(serial.master, &t);
    cfmakeraw(&t);
    tcsetattr(serial.master, TCSANOW, &t);
    unlink(link_path);
    if (symlink(name, link_path))
        return -1;
    return 0;
}

// --- profile: cycles spent in the firmware's idle loop ------------------------
// Klipper's AVR idle loop (sei; nop; cli; check tasks_status; loop) spans
// [idle_start, idle_end) in flash; every other cycle is work (interrupts too).
static struct {
    uint32_t idle_start, idle_end;
    uint64_t idle_cycles;
    // Cycles by flash word address, kept when asked (pcprof on): where the
    // work goes (devtools/simavr/pcprof.py names the functions)
    uint64_t *by_pc;
} prof;

static int reply(const char *fmt, ...);

// pcprof on|off|dump FILE: "word_address cycles" lines of non-zero entries
static int
pc_profile(const char *what, const char *path)
{
    size_t words = (avr->flashend + 1) / 2;
    if (!strcmp(what, "on")) {
        free(prof.by_pc);
        prof.by_pc = calloc(words, sizeof(*prof.by_pc));
        return reply(prof.by_pc ? "ok" : "error out of memory");
    }
    if (!strcmp(what, "off")) {
        free(prof.by_pc);
        prof.by_pc = NULL;
        return reply("ok");
    }
    if (!strcmp(what, "dump") && prof.by_pc && *path) {
        FILE *f = fopen(path, "w");
        if (!f)
            return reply("error cannot write %s", path);
        for (size_t i = 0; i < words; i++)
            if (prof.by_pc[i])
                fprintf(f, "%zu %llu\n", i, (unsigned long long)prof.by_pc[i]);
        fclose(f);
        return reply("ok");
    }
    return reply("error pcprof on|off|dump FILE (after on)");
}

// --- the firmware's clock: no Timer1 overflow lost -----------------------------
// Klipper's AVR clock is timer_high:TCNT1; a wrap timer adds each overflow
// to timer_high at TCNT1 0x0000 or, late, at 0x8000, so its steps come 32768
// to 98304 cycles apart. A gap of two periods is an overflow the firmware
// never counted: its clock fell 65536 ticks behind for good (what a late
// simulated compare match did before flowloop's simavr timer fix).
// One such loss is Klipper's own, on hardware too: when a timer ISR that
// has fallen behind shuts the MCU down ("Rescheduled timer in the past"),
// the wrap timer is already late, and the shutdown functions run for
// ~1.2 ms with interrupts off (move_reset frees every queued move) before
// timer_reset adds it back. Past 32768 ticks late, the ISR's 16-bit compare
// reads its waketime as in the future, arms OCR1A = 0x0000, and the next
// overflow sets the flag already set. So a gap during which the firmware
// was shut down (Klipper's SchedStatus.shutdown_status) is counted apart.
#define LOST_OVERFLOW_GAP 0x1c000
static struct {
    uint16_t address;     // timer_high's data address, or 0: not watched
    uint16_t shutdown;    // SchedStatus.shutdown_status's address, or 0
    uint16_t last_high;
    avr_cycle_count_t last_change;
    int shut_down_in_gap; // the firmware was shut down since the last step
    unsigned long lost, lost_in_shutdown;
} fwclock;

static void
watch_firmware_clock(void)
{
    uint16_t a = fwclock.address;
    uint16_t high = avr->data[a] | (avr->data[a + 1] << 8);
    if (fwclock.shutdown && avr->data[fwclock.shutdown])
        fwclock.shut_down_in_gap = 1;
    if (high == fwclock.last_high)
        return;
    if (high != (uint16_t)(fwclock.last_high + 1)) {
        // first sight, or the MCU reset (watchdog): count from its next step
        fwclock.last_high = high;
        fwclock.last_change = 0;
        fwclock.shut_down_in_gap = 0;
        return;
    }
    if (fwclock.last_change && avr->cycle - fwclock.last_change > LOST_OVERFLOW_GAP) {
        if (fwclock.shut_down_in_gap) {
            fwclock.lost_in_shutdown++;
            printf("fil_harness: the firmware's clock missed a Timer1 overflow"
                   " at %.6f s (timer_high %u) while the firmware was shut"
                   " down: Klipper's own (its late wrap timer re-added)\n",
                   sim_seconds(), high);
        } else {
            fwclock.lost++;
            printf("fil_harness: the firmware's clock missed a Timer1 overflow"
                   " at %.6f s (timer_high %u)\n", sim_seconds(), high);
        }
    }
    fwclock.last_high = high;
    fwclock.last_change = avr->cycle;
    fwclock.shut_down_in_gap = 0;
}

// --- pacing -------------------------------------------------------------------
// lag_s: how far simulated time is behind the wall clock. own_lag_s: the
// part of it the harness made itself (CPU time it ran beyond the simulated
// time it produced while behind), as opposed to time it was not running at
// all (descheduled, or the machine stalled): only the first says the
// simulation is too slow for real time.
static struct {
    struct timespec start;
    double lag_s, max_lag_s, max_lag_at_s, reported_lag_s;
    double own_lag_s, max_own_lag_s;
    double last_sim_s, last_cpu_s;
} pace;

static double
cpu_seconds(void)
{
    struct timespec now;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &now);
    return now.tv_sec + now.tv_nsec * 1e-9;
}

static double
wall_seconds(void)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (now.tv_sec - pace.start.tv_sec) + (now.tv_nsec - pace.start.tv_nsec) * 1e-9;
}

// --- control socket -------------------------------------------------------------
static int listen_fd = -1, client_fd = -1;
static char cmd_buf[512];
static int cmd_len;

static int
reply(const char *fmt, ...)
{
    char out[1024];
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(out, sizeof(out) - 1, fmt, ap);
    va_end(ap);
    if (n > (int)sizeof(out) - 2)
        n = sizeof(out) - 2;
    out[n++] = '\n';
    if (client_fd >= 0 && write(client_fd, out, n) != n) {
        close(client_fd);
        client_fd = -1;
    }
    return 0;
}

static int
command(char *line)
{
    char name[32] = "";
    double a = 0, b = 0;
    int n = sscanf(line, "%31s %lf %lf", name, &a, &b);
    if (n < 1)
        return reply("error empty command");
    if (!strcmp(name, "status")) {
        return reply("cycle=%llu sim_s=%.6f wall_s=%.6f cpu_s=%.6f lag_ms=%.3f"
                     " max_lag_ms=%.3f max_lag_at_s=%.3f max_own_lag_ms=%.3f"
                     " steps=%ld filament_mm=%.6f counts=%ld"
                     " grip=%.6f fault=%s frames=%lu spi_bytes=%lu"
                     " to_host=%lu from_host=%lu dropped=%lu idle_cycles=%llu"
                     " lost_overflows=%lu lost_overflows_in_shutdown=%lu",
                     (unsigned long long)avr->cycle, sim_seconds(), wall_seconds(),
                     cpu_seconds(), pace.lag_s * 1e3, pace.max_lag_s * 1e3,
                     pace.max_lag_at_s, pace.max_own_lag_s * 1e3, fil.steps, fil.mm,
                     shaft_counts(), grip_now(), fault_names[chip.fault],
                     chip.frames, chip.bytes, serial.to_host, serial.from_host,
                     serial.dropped, (unsigned long long)prof.idle_cycles,
                     fwclock.lost, fwclock.lost_in_shutdown);
    }
    if (!strcmp(name, "grip") && n >= 2) {  // grip G [RAMP_SECONDS]
        double now = sim_seconds();
        fil.grip0 = grip_now();
        fil.grip1 = a;
        fil.t0 = now;
        fil.t1 = n >= 3 ? now + b : now;
        return reply("ok grip=%.6f at sim_s=%.6f", a, now);
    }
    if (!strcmp(name, "fault")) {
        char which[32] = "";
        sscanf(line, "%*s %31s", which);
        for (unsigned i = 0; i < sizeof(fault_names) / sizeof(*fault_names); i++)
            if (!strcmp(which, fault_names[i])) {
                chip.fault = i;
                drive_miso();
                return reply("ok fault=%s at sim_s=%.6f", which, sim_seconds());
            }
        return reply("error unknown fault '%s'", which);
    }
    if (!strcmp(name, "stall") && n >= 2) {  // stall MS: the next SPI byte
        if (chip.software)
            return reply("error stall needs hardware SPI");
        chip.stall_cycles = (avr_cycle_count_t)(a * freq_hz / 1000.);
        return reply("ok stall_ms=%.3f", a);
    }
    if (!strcmp(name, "heater")) {  // the heater's duty since the last ask
        double duty = heater_duty();
        return reply("duty=%.6f sim_s=%.6f", duty, sim_seconds());
    }
    if (!strcmp(name, "adc") && n >= 2) {  // thermistor pin voltage in mV
        set_adc_mv((uint32_t)a);
        return reply("ok adc_mv=%u", (unsigned)a);
    }
    if (!strcmp(name, "cycles")) {
        return reply("cycle=%llu sim_s=%.6f", (unsigned long long)avr->cycle,
                     sim_seconds());
    }
    if (!strcmp(name, "peek") && n >= 2) {  // a 16-bit word in data space
        uint32_t addr = (uint32_t)a;
        if (addr + 1 >= avr->ramend + 1u)
            return reply("error address %u out of range", addr);
        return reply("value=%u cycle=%llu lag_ms=%.3f",
                     avr->data[addr] | (avr->data[addr + 1] << 8),
                     (unsigned long long)avr->cycle, pace.lag_s * 1e3);
    }
    if (!strcmp(name, "pcprof")) {
        char what[8] = "", path[200] = "";
        sscanf(line, "%*s %7s %199s", what, path);
        return pc_profile(what, path);
    }
    if (!strcmp(name, "reset_lag")) {
        pace.max_lag_s = pace.max_lag_at_s = pace.max_own_lag_s = 0;
        return reply("ok");
    }
    return reply("error unknown command '%s'", name);
}

static void
serve_control(void)
{
    if (client_fd < 0) {
        client_fd = accept4(listen_fd, NULL, NULL, SOCK_NONBLOCK);
        cmd_len = 0;
        if (client_fd < 0)
            return;
    }
    for (;;) {
        int n = read(client_fd, cmd_buf + cmd_len, sizeof(cmd_buf) - 1 - cmd_len);
        if (n == 0 || (n < 0 && errno != EAGAIN && errno != EINTR)) {
            close(client_fd);
            client_fd = -1;
            return;
        }
        if (n < 0)
            return;
        cmd_len += n;
        char *nl;
        while (client_fd >= 0 && (nl = memchr(cmd_buf, '\n', cmd_len))) {
            *nl = 0;
            command(cmd_buf);
            int rest = cmd_len - (nl + 1 - cmd_buf);
            memmove(cmd_buf, nl + 1, rest);
            cmd_len = rest;
        }
        if (client_fd < 0)
            return;
        if (cmd_len >= (int)sizeof(cmd_buf) - 1)
            cmd_len = 0;
    }
}

static int
open_control(const char *path)
{
    struct sockaddr_un addr = { .sun_family = AF_UNIX };
    if (strlen(path) >= sizeof(addr.sun_path))
        return -1;
    strcpy(addr.sun_path, path);
    unlink(path);
    listen_fd = socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK, 0);
    if (listen_fd < 0 || bind(listen_fd, (void *)&addr, sizeof(addr))
        || listen(listen_fd, 2))
        return -1;
    return 0;
}

// Wait until the wall clock reaches sim time, serving the pty and the socket
static void
wait_and_serve(double sim_s)
{
    double ahead = sim_s - wall_seconds(), cpu_s = cpu_seconds();
    double ran_over = (cpu_s - pace.last_cpu_s) - (sim_s - pace.last_sim_s);
    pace.last_sim_s = sim_s;
    pace.last_cpu_s = cpu_s;
    struct pollfd fds[3] = {
        { .fd = serial.master, .events = POLLIN },
        { .fd = client_fd >= 0 ? client_fd : listen_fd, .events = POLLIN },
    };
    if (ahead < 0) {
        pace.lag_s = -ahead;
        if (pace.lag_s > pace.max_lag_s) {
            pace.max_lag_s = pace.lag_s;
            pace.max_lag_at_s = sim_s;
        }
        pace.own_lag_s += ran_over;
        if (pace.own_lag_s < 0)
            pace.own_lag_s = 0;
        if (pace.own_lag_s > pace.lag_s)
            pace.own_lag_s = pace.lag_s;
        if (pace.own_lag_s > pace.max_own_lag_s)
            pace.max_own_lag_s = pace.own_lag_s;
        ahead = 0;
    } else {
        pace.lag_s = pace.own_lag_s = 0;
    }
    struct timespec ts = { (time_t)ahead, (long)((ahead - (time_t)ahead) * 1e9) };
    ppoll(fds, 2, &ts, NULL);
    read_pty();
    serve_control();
}

static void
on_signal(int sig)
{
    stop_requested = 1;
}

static void
usage(void)
{
    fprintf(stderr,
            "usage: fil_harness --elf klipper.elf --pty PATH --control SOCKET\n"
            "  [--freq HZ] [--cs PG0] [--sw-spi SCK,MISO] [--step PA4 --dir PA6]\n"
            "  [--dir-invert] [--both-edges] [--mm-per-step MM]"
            " [--counts-per-mm N]\n"
            "  [--heater PB4] [--adc-channel 13] [--adc-mv MV]"
            " [--idle-pc START,END] [--clock-high ADDR]\n"
            "  [--shutdown-flag ADDR]\n");
    exit(2);
}

int
main(int argc, char **argv)
{
    const char *elf = NULL, *pty_path = NULL, *control = NULL;
    struct pin step = { 0 }, dir = { 0 };
    uint32_t adc_mv = 0;
    setvbuf(stdout, NULL, _IOLBF, 0);
    fil.mm_per_step = 7.71 / 3200;
    fil.counts_per_mm = POSITIONS / (M_PI * 3.17);
    chip.cs = (struct pin){ 'G', 0 };
    for (int i = 1; i < argc; i++) {
        const char *opt = argv[i], *val = i + 1 < argc ? argv[i + 1] : NULL;
        int takes = 1;
        if (!strcmp(opt, "--dir-invert")) { fil.dir_invert = 1; takes = 0; }
        else if (!strcmp(opt, "--both-edges")) { fil.both_edges = 1; takes = 0; }
        else if (!val) usage();
        else if (!strcmp(opt, "--elf")) elf = val;
        else if (!strcmp(opt, "--pty")) pty_path = val;
        else if (!strcmp(opt, "--control")) control = val;
        else if (!strcmp(opt, "--freq")) freq_hz = strtoul(val, NULL, 10);
        else if (!strcmp(opt, "--mm-per-step")) fil.mm_per_step = atof(val);
        else if (!strcmp(opt, "--counts-per-mm")) fil.counts_per_mm = atof(val);
        else if (!strcmp(opt, "--adc-channel")) hot.adc_channel = atoi(val);
        else if (!strcmp(opt, "--idle-pc")) {
            if (sscanf(val, "%x,%x", &prof.idle_start, &prof.idle_end) != 2)
                usage();
        }
        else if (!strcmp(opt, "--clock-high"))
            fwclock.address = strtoul(val, NULL, 16);
        else if (!strcmp(opt, "--shutdown-flag"))
            fwclock.shutdown = strtoul(val, NULL, 16);
        else if (!strcmp(opt, "--adc-mv")) adc_mv = strtoul(val, NULL, 10);
        else if (!strcmp(opt, "--cs")) { if (parse_pin(val, &chip.cs)) usage(); }
        else if (!strcmp(opt, "--step")) { if (parse_pin(val, &step)) usage(); }
        else if (!strcmp(opt, "--dir")) { if (parse_pin(val, &dir)) usage(); }
        else if (!strcmp(opt, "--heater")) {
            if (parse_pin(val, &hot.heater)) usage();
            hot.enabled = 1;
        } else if (!strcmp(opt, "--sw-spi")) {
            char a[8] = "", b[8] = "";
            if (sscanf(val, "%3[^,],%3s", a, b) != 2 || parse_pin(a, &chip.sck)
                || parse_pin(b, &chip.miso))
                usage();
            chip.software = 1;
        } else usage();
        i += takes;
    }
    if (!elf || !pty_path || !control)
        usage();

    elf_firmware_t fw;
    memset(&fw, 0, sizeof(fw));
    if (elf_read_firmware(elf, &fw)) {
        fprintf(stderr, "fil_harness: cannot read firmware %s\n", elf);
        return 1;
    }
    if (!fw.mmcu[0])
        strcpy(fw.mmcu, "atmega2560");
    fw.frequency = freq_hz;
    avr = avr_make_mcu_by_name(fw.mmcu);
    if (!avr) {
        fprintf(stderr, "fil_harness: simavr has no core '%s'\n", fw.mmcu);
        return 1;
    }
    avr_init(avr);
    avr->log = LOG_ERROR;
    avr->vcc = avr->avcc = avr->aref = 5000;
    avr_load_firmware(avr, &fw);
    avr->frequency = freq_hz;

    if (open_pty(pty_path)) {
        fprintf(stderr, "fil_harness: cannot open a pty at %s: %s\n", pty_path,
                strerror(errno));
        return 1;
    }
    if (open_control(control)) {
        fprintf(stderr, "fil_harness: cannot listen on %s: %s\n", control,
                strerror(errno));
        return 1;
    }
    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~AVR_UART_FLAG_STDIO;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'),
                                          UART_IRQ_OUTPUT), on_uart_out, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'),
                                          UART_IRQ_OUT_XON), on_xon, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'),
                                          UART_IRQ_OUT_XOFF), on_xoff, NULL);

    avr_irq_register_notify(pin_irq(chip.cs), on_cs, NULL);
    if (chip.software) {
        chip.miso_irq = pin_irq(chip.miso);
        avr_irq_register_notify(pin_irq(chip.sck), on_sck, NULL);
        drive_miso();
    } else {
        avr_irq_t *spi_out = spi_irq(SPI_IRQ_OUTPUT);
        if (!spi_out) {
            fprintf(stderr, "fil_harness: simavr's atmega2560 has no SPI\n");
            return 1;
        }
        avr_irq_register_notify(spi_out, on_spi_byte, NULL);
    }
    if (step.port) {
        avr_irq_register_notify(pin_irq(step), on_step, NULL);
        avr_irq_register_notify(pin_irq(dir), on_dir, NULL);
    }
    if (hot.enabled)
        avr_irq_register_notify(pin_irq(hot.heater), on_heater, NULL);
    if (adc_mv)
        set_adc_mv(adc_mv);

    signal(SIGTERM, on_signal);
    signal(SIGINT, on_signal);
    signal(SIGPIPE, SIG_IGN);
    clock_gettime(CLOCK_MONOTONIC, &pace.start);
    pace.last_cpu_s = cpu_seconds();
    printf("fil_harness: running %s at %u Hz, serial on %s, control on %s,"
           " EMS22 on %s SPI\n", elf, freq_hz, pty_path, control,
           chip.software ? "software" : "hardware");

    // Serve every 0.5 ms of simulated time; report falling behind once per
    // 50 ms more of lag.
    avr_cycle_count_t check_every = freq_hz / 2000, next_check = check_every;
    for (;;) {
        uint32_t pc = avr->pc;
        avr_cycle_count_t before = avr->cycle;
        int state = avr_run(avr);
        if (pc >= prof.idle_start && pc < prof.idle_end)
            prof.idle_cycles += avr->cycle - before;
        if (prof.by_pc)
            prof.by_pc[pc / 2] += avr->cycle - before;
        if (state == cpu_Done || state == cpu_Crashed) {
            printf("fil_harness: the AVR stopped (%s) at %.6f s\n",
                   state == cpu_Done ? "done" : "crashed", sim_seconds());
            return 1;
        }
        if (avr->cycle < next_check)
            continue;
        next_check = avr->cycle + check_every;
        if (fwclock.address)
            watch_firmware_clock();
        wait_and_serve(sim_seconds());
        if (pace.lag_s > pace.reported_lag_s + 0.05) {
            printf("fil_harness: simulation behind the wall clock by %.0f ms"
                   " (%.0f ms of it running slower than real time) at %.3f s\n",
                   pace.lag_s * 1e3, pace.own_lag_s * 1e3, sim_seconds());
            pace.reported_lag_s = pace.lag_s;
        } else if (pace.lag_s == 0) {
            pace.reported_lag_s = 0;
        }
        if (stop_requested)
            break;
    }
    printf("fil_harness: stopped at %.6f s, max lag %.1f ms at %.3f s (%.1f ms"
           " running slower than real time), %lu frames\n", sim_seconds(),
           pace.max_lag_s * 1e3, pace.max_lag_at_s, pace.max_own_lag_s * 1e3,
           chip.frames);
    unlink(pty_path);
    unlink(control);
    return 0;
}
