#ifndef __BOARD_IRQ_H
#define __BOARD_IRQ_H
static inline void irq_disable(void) {}
static inline void irq_enable(void) {}
#endif
