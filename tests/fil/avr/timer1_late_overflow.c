// Timer1 overflows while a multi-cycle instruction runs (here a RET, 5
// cycles on the atmega2560), so simavr handles the overflow a few cycles
// late. With OCR1A = 0x0000 (Klipper's wrap timer, which counts Timer1
// overflows into its clock's high word) the compare must still match one
// timer tick after every overflow, whatever the next instruction does:
// here nothing, a write of OCR1B (Klipper's timer_repeat_set) or a rewrite
// of OCR1A, either of which makes simavr re-arm the timer's cycle timers.
// For each phase k the overflow falls k cycles earlier in the same code;
// TIFR1 is read some 30 cycles after it, and must show TOV1 and OCF1A.
// tests/fil/test_fil_timer1.py builds and runs it.
#include <avr/io.h>
#include <avr/sleep.h>
#include <stdint.h>

#define PHASES 48
#define MEM(reg) "i"(_SFR_MEM_ADDR(reg))

volatile uint8_t after_nothing[PHASES], after_ocr1b[PHASES], after_ocr1a[PHASES];

// TCNT1 = tcnt; 40 cycles; rcall (4) and ret (5); then NEXT; 24 cycles;
// out = TIFR1. The overflow falls 0x10000 - tcnt cycles after the write.
#define PHASE(NEXT, out, tcnt) asm volatile(                           \
    "sts %[tcnth], %B[t]\n\t"                                           \
    "sts %[tcntl], %A[t]\n\t"                                           \
    ".rept 40\n\tnop\n\t.endr\n\t"                                      \
    "rcall 1f\n\t"                                                      \
    NEXT "\n\t"                                                         \
    ".rept 24\n\tnop\n\t.endr\n\t"                                      \
    "lds %[f], %[tifr]\n\t"                                             \
    "rjmp 2f\n"                                                         \
    "1: ret\n"                                                          \
    "2:\n"                                                              \
    : [f] "=&r"(out)                                                    \
    : [t] "r"(tcnt), [tcnth] MEM(TCNT1H), [tcntl] MEM(TCNT1L),          \
      [tifr] MEM(TIFR1), [ocr1bl] MEM(OCR1BL), [ocr1al] MEM(OCR1AL),    \
      [zero] "r"((uint8_t)0))

int
main(void)
{
    TIMSK1 = 0;         // the flags are polled, as Klipper polls TOV1
    TCCR1A = 0;         // normal mode, as Klipper runs Timer1
    OCR1A = 0;
    OCR1B = 0x8000;
    TCCR1B = 1 << CS10;
    for (uint8_t k = 0; k < PHASES; k++) {
        uint16_t tcnt = 0xffc0 + k;
        uint8_t f;
        TIFR1 = 0xff;
        PHASE("nop", f, tcnt);
        after_nothing[k] = f;
        TIFR1 = 0xff;
        PHASE("sts %[ocr1bl], %[zero]", f, tcnt);   // OCR1B stays 0x8000
        after_ocr1b[k] = f;
        TIFR1 = 0xff;
        PHASE("sts %[ocr1al], %[zero]", f, tcnt);   // OCR1A stays 0x0000
        after_ocr1a[k] = f;
    }
    sleep_enable();
    asm volatile("cli\n\tsleep");   // simavr ends the run here
    for (;;)
        ;
}
