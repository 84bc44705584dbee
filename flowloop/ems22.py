"""EMS22A magnetic encoder: the MCU protocol flowloop's firmware speaks.

The message formats are shared by the klippy adapters (to look the commands
up) and by the firmware check that tells users to rebuild.
"""

CONFIG_CMD = "config_ems22 oid=%c spi_oid=%c"
QUERY_CMD = "query_ems22 oid=%c clock=%u rest_ticks=%u time_shift=%c"

