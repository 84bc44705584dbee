"""The SPI mode, judged against the chip rather than against flowloop's own
model of it. On software SPI the EMS22 model sees only the SCK pin's edges
and drives MISO 375 ns after each rising edge, as the datasheet gives it; on
hardware SPI it answers from the clock edges of the mode the firmware wrote
into SPCR. A mode whose reads do not hold the frame where flowloop looks for
it must show up as errors and a fault, never as a wrong filament position.

Found here: Klipper's spi_software reads MISO half a clock after the leading
edge in modes 0 and 2 and just after the trailing edge in modes 1 and 3. So
in mode 0 it reads the bit the chip drove on that same rising edge (the
hardware SPI reads the one before), and in mode 3 it reads the new bit once
it is valid, about 6 AVR cycles after the edge (hardware: the old one).
flowloop decodes every mode as the hardware reads it, so on software SPI only
modes 1 and 2 (the default) give data: those two faulted as `misaligned`
(never a wrong position), and klippy now refuses them at start-up
(tests/klippy/flow_sensor_fail_soft_spi_mode.test)."""

from __future__ import annotations

import pytest

from tests.fil.conftest import COUNTS_PER_MM, fil_printer, settle

SOFTWARE = {"cs": "PG0", "sclk": "PC0", "miso": "PC2"}
SOFTWARE_PINS = """spi_software_sclk_pin: PC0
spi_software_mosi_pin: PC1
spi_software_miso_pin: PC2
spi_speed: 500000"""


def sections(spi_mode: int, software: bool) -> str:
    return f"""
[flow_sensor filament]
sensor_type: ems22
cs_pin: PG0
{SOFTWARE_PINS if software else ""}
spi_mode: {spi_mode}
grip_window: 8
"""


def _extrude_20mm(printer):
    """(sensor status before, after, model filament mm moved)"""
    before = settle(printer, 0.6)
    model_before = float(printer.sim.status()["filament_mm"])
    printer.gcode("M83\nG1 E20 F1500\nM400")
    after = settle(printer)
    return before, after, float(printer.sim.status()["filament_mm"]) - model_before


@pytest.mark.parametrize("spi_mode,software", [(1, True), (2, True), (0, False)])
def test_a_mode_that_reads_the_frame_gives_the_models_filament(
        fil_build, spi_mode, software):
    with fil_printer(fil_build, sections(spi_mode, software),
                     SOFTWARE if software else None) as printer:
        before, after, model_mm = _extrude_20mm(printer)
    assert after["errors"] == {} and after["fault"] is None
    assert after["samples"] - before["samples"] > 250
    sensor_mm = after["filament_position"] - before["filament_position"]
    assert abs(sensor_mm - model_mm) <= 2.5 / COUNTS_PER_MM
    assert after["grip"] == pytest.approx(1.0, rel=0.002)


@pytest.mark.parametrize("spi_mode", [0, 3])
def test_a_mode_software_spi_cannot_read_is_refused_at_start(fil_build, spi_mode):
    with pytest.raises(pytest.fail.Exception) as refused:  # "did not start"
        with fil_printer(fil_build, sections(spi_mode, True), SOFTWARE):
            pass
    assert (f"spi_mode {spi_mode} cannot read an EMS22 on software SPI"
            in str(refused.value)), refused.value
