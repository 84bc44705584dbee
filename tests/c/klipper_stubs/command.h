#ifndef __COMMAND_H
#define __COMMAND_H
#include <stdio.h>
#include <stdlib.h>
#define DECL_COMMAND(FUNC, MSG) extern int decl_command_unused
#define shutdown(msg) do { printf("shutdown %s\n", msg); exit(2); } while (0)
#endif
