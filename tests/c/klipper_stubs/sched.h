#ifndef __SCHED_H
#define __SCHED_H
#include <stddef.h>
#include <stdint.h>
#define container_of(ptr, type, member) \
    ((type *)((char *)(ptr) - offsetof(type, member)))
struct timer {
    struct timer *next;
    uint_fast8_t (*func)(struct timer *);
    uint32_t waketime;
};
enum { SF_DONE = 0, SF_RESCHEDULE = 1 };
struct task_wake {
    uint8_t wake;
};
void sched_add_timer(struct timer *);
void sched_del_timer(struct timer *);
void sched_wake_task(struct task_wake *w);
uint8_t sched_check_wake(struct task_wake *w);
#define DECL_TASK(FUNC) extern int decl_task_unused
#define DECL_SHUTDOWN(FUNC) extern int decl_shutdown_unused
#endif
