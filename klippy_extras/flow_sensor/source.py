# [flow_sensor NAME] with sensor_type: ems22: the real chip on an MCU SPI
# bus, read by flowloop's firmware command (mcu_sensor/sensor_ems22.c) on a
# timer; the serial thread queues its messages (Klipper's BulkDataQueue) and
# the sensor's reactor timer hands them to the pipeline (the package's
# __init__ loads it).
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import logging

from flowloop.host.firmware import FLASH_COMMAND
from flowloop.sensor import ems22
from flowloop.sensor import pipeline as fl_pipeline

if (__package__ or '').startswith('klippy.'):
    # Kalico: klippy.plugins.flow_sensor, klippy's modules two up
    from ...extras import bulk_sensor, bus
else:   # Klipper: klippy/extras/flow_sensor/, extras one up
    from .. import bulk_sensor, bus

MIN_MSG_TIME = 0.100
REBUILD_MSG = ("MCU '{}' firmware has no EMS22 sensor support: build and "
               "flash it with the sensor command: " + FLASH_COMMAND)


class Ems22Source:
    """The real EMS22 on an MCU SPI bus: the MCU reads it on a timer, the
    serial thread only queues its messages, a reactor timer decodes them."""

    simulation = None   # a real sensor: no simulation facts in its status

    def __init__(self, config, sensor):
        self.sensor = sensor
        self.printer = config.get_printer()
        self.reactor = self.printer.get_reactor()
        self.spi_speed = config.getint('spi_speed', ems22.MAX_SPI_HZ,
                                       minval=ems22.MIN_SPI_HZ,
                                       maxval=ems22.MAX_SPI_HZ)
        self.software_spi = config.get('spi_software_sclk_pin', None) is not None
        problem = (ems22.software_spi_mode_problem(sensor.spi_mode)
                   if self.software_spi else None)
        if problem:
            raise config.error(f"Section [{sensor.section}], options spi_mode and"
                               f" spi_software_sclk_pin: {problem}")
        self.spi = bus.MCU_SPI_from_config(config, sensor.spi_mode,
                                           default_speed=self.spi_speed)
        self.mcu = mcu = self.spi.get_mcu()
        self.oid = mcu.create_oid()
        mcu.register_config_callback(self._build_config)
        # the serial thread queues the messages, a reactor timer decodes them
        # (each host's own default message: by format or by name)
        self.bulk_queue = bulk_sensor.BulkDataQueue(mcu, oid=self.oid)
        self.query_cmd = None
        self.start_clock = None
        self.rest_ticks = self.time_shift = 0
        self.restart_pending = False

    def _build_config(self):
        mcu = self.mcu
        if (mcu.try_lookup_command(ems22.QUERY_CMD) is None
                or mcu.try_lookup_command(ems22.CONFIG_CMD) is None):
            raise self.printer.config_error(
                f"[{self.sensor.section}] " + REBUILD_MSG.format(mcu.get_name()))
        mcu_freq = mcu.seconds_to_clock(1.)
        self._check_read_time(mcu_freq)
        max_read_ticks = ems22.max_read_ticks(self.spi_speed, self.software_spi,
                                              mcu_freq)
        bit_offset = ems22.bit_offset_for_mode(self.sensor.spi_mode)
        mcu.add_config_cmd(f"config_ems22 oid={self.oid}"
                           f" spi_oid={self.spi.get_oid()}"
                           f" max_read_ticks={max_read_ticks}"
                           f" bit_offset={bit_offset}")
        mcu.add_config_cmd(f"query_ems22 oid={self.oid} clock=0 rest_ticks=0"
                           " time_shift=0 max_bytes=0", on_restart=True)
        self.time_shift = ems22.time_shift_for(mcu_freq)
        self.query_cmd = mcu.lookup_command(
            ems22.QUERY_CMD, cq=self.spi.get_command_queue())

    def _check_read_time(self, mcu_freq):
        period = self.sensor.sample_period
        shortest = ems22.min_sample_period_s(self.spi_speed, self.software_spi,
                                             mcu_freq)
        if period >= shortest:
            return
        read_us = 1e6 * ems22.read_time_s(self.spi_speed, self.software_spi,
                                          mcu_freq)
        if self.software_spi:
            option, fix = 'spi_software_sclk_pin', "use a hardware SPI bus"
        else:
            option, fix = 'spi_speed', "raise spi_speed"
        raise self.printer.config_error(
            f"Section [{self.sensor.section}], options {option} and"
            f" sample_period: a read on this bus takes about {read_us:.0f} us,"
            f" more than {100 * ems22.MAX_READ_SHARE:.0f}% of sample_period"
            f" {period:g} s; {fix} or set sample_period >= {shortest:.4f}")

    def connect(self, sensor):
        pass

    def start(self):
        self.rest_ticks = self.mcu.seconds_to_clock(self.sensor.sample_period)
        self._start_query()

    def temp_c(self, eventtime):
        return self.sensor.heater.get_temp(eventtime)[0]

    def hotend_params(self):
        return None     # a real hotend: its heater reads it

    def power(self, eventtime):
        return self.sensor.heater.get_status(eventtime)['power']

    def timing(self):
        return fl_pipeline.SampleTiming(self.start_clock, self.rest_ticks,
                                        self.time_shift,
                                        self.mcu.clock_to_print_time)

    def _start_query(self):
        self.sensor.pipeline.restart()
        print_time = self.mcu.estimated_print_time(self.reactor.monotonic())
        self.start_clock = self.mcu.print_time_to_clock(print_time + MIN_MSG_TIME)
        max_bytes = ems22.message_bytes(self.rest_ticks,
                                        self.mcu.seconds_to_clock(1.))
        self.query_cmd.send([self.oid, self.start_clock & 0xffffffff,
                             self.rest_ticks, self.time_shift, max_bytes],
                            reqclock=self.start_clock)

    def _restart_query(self):
        # Stop the MCU and drop what it sent before the stop (as angle.py
        # does), so that no old record is timed against the new start
        logging.warning("flow_sensor %s: MCU '%s' fell %d reads behind and"
                        " lost count of them; restarting the sensor query",
                        self.sensor.name, self.mcu.get_name(), ems22.MAX_PENDING)
        self.restart_pending = True
        self.query_cmd.send_wait_ack([self.oid, 0, 0, 0, 0])
        self.bulk_queue.clear_queue()
        self._start_query()
        self.restart_pending = False

    def catch_up(self):
        messages = [(params['sequence'], params['data'])
                    for params in self.bulk_queue.pull_queue()]
        if not messages:
            return
        self.sensor.process(messages)
        # After this batch's good samples are timed against the old start
        if self.sensor.pipeline.time_lost and not self.restart_pending:
            self._restart_query()

    def sync(self, until=None):
        self.catch_up()
