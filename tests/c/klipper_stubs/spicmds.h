#ifndef __SPICMDS_H
#define __SPICMDS_H
#include <stdint.h>
struct spidev_s;
struct spidev_s *spidev_oid_lookup(uint8_t oid);
int spidev_have_cs_pin(struct spidev_s *spi);
void spidev_transfer(struct spidev_s *spi, uint8_t receive_data
                     , uint8_t data_len, uint8_t *data);
#endif
