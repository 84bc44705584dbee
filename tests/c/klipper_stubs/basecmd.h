// Host stand-ins for the Klipper headers sensor_ems22.c includes, so that
// tests/c/ems22_firmware_test.c can run the firmware's own code (one oid).
#ifndef __BASECMD_H
#define __BASECMD_H
#include <stdint.h>
void *oid_alloc(uint8_t oid, void *type, uint16_t size);
void *oid_lookup(uint8_t oid, void *type);
void *oid_only(void *type);
// This stand-in holds one oid at most: the body runs once, for oid 0.
#define foreach_oid(pos, data, oidtype) \
    for ((pos) = 0, (data) = oid_only(oidtype); (data); (data) = NULL)
#endif
