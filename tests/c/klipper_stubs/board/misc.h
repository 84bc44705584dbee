#ifndef __BOARD_MISC_H
#define __BOARD_MISC_H
#include <stdint.h>
uint32_t timer_read_time(void);
#define timer_from_us(us) ((uint32_t)(us) * 16) // a 16 MHz MCU
#endif
