// A small AVR test program on flowloop's patched simavr: run it until it
// sleeps with interrupts off (simavr's end of a program), then print the
// data bytes asked for, one line each: "data 0b 0b ...".
//   run_program ELF [ADDR:LEN]...   (ADDR in hex, data space)
#include <stdio.h>
#include <string.h>

#include "sim_avr.h"
#include "sim_elf.h"

#define MAX_CYCLES 100000000ULL

int
main(int argc, char **argv)
{
    if (argc < 2) {
        fprintf(stderr, "usage: %s ELF [ADDR:LEN]...\n", argv[0]);
        return 2;
    }
    elf_firmware_t fw;
    memset(&fw, 0, sizeof(fw));
    if (elf_read_firmware(argv[1], &fw)) {
        fprintf(stderr, "cannot read %s\n", argv[1]);
        return 2;
    }
    if (!fw.mmcu[0])
        strcpy(fw.mmcu, "atmega2560");
    if (!fw.frequency)
        fw.frequency = 16000000;
    avr_t *avr = avr_make_mcu_by_name(fw.mmcu);
    if (!avr) {
        fprintf(stderr, "simavr has no core '%s'\n", fw.mmcu);
        return 2;
    }
    avr_init(avr);
    avr->log = LOG_ERROR;
    avr_load_firmware(avr, &fw);
    int state = cpu_Running;
    while (state != cpu_Done && state != cpu_Crashed && avr->cycle < MAX_CYCLES)
        state = avr_run(avr);
    if (state != cpu_Done) {
        fprintf(stderr, "the program did not end (state %d at cycle %llu)\n",
                state, (unsigned long long)avr->cycle);
        return 1;
    }
    for (int i = 2; i < argc; i++) {
        unsigned addr, len;
        if (sscanf(argv[i], "%x:%u", &addr, &len) != 2
            || addr + len > avr->ramend + 1u) {
            fprintf(stderr, "bad ADDR:LEN '%s'\n", argv[i]);
            return 2;
        }
        printf("data");
        for (unsigned j = 0; j < len; j++)
            printf(" %02x", avr->data[addr + j]);
        printf("\n");
    }
    return 0;
}
