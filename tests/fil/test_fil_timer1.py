"""simavr's Timer1 against the hardware, where Klipper's AVR clock depends
on it: a compare match with OCR1A = 0x0000 (Klipper's wrap timer, which
counts Timer1 overflows into timer_high) must come one tick after every
overflow, also when simavr handles the overflow a few cycles late because
it fell inside a multi-cycle instruction.

Found here: flowloop's first timer fix (issue 24) made such a late match
fire from a cycle timer one cycle later; an OCR1A, OCR1B, TCNT1 or TCCR1
write in the next instruction re-arms every Timer1 cycle timer and keeps
only the matches still to come in the period, so it dropped that one and
the match came a whole period (65536 cycles) late, as before the fix. The
fix matches at once, in the overflow's own handler (devtools/simavr
TIMER_PATCH_TO). Without any fix the phases where the overflow falls 2 to 4
cycles before the end of the RCALL or the RET come back without OCF1A;
with the first fix, those of the RET followed by the OCR1x write.

Klipper's own code never wrote a low OCR1x byte right after such an
instruction (the high byte's 2-cycle store always comes first), so the
missed overflow of issue 38 was not this: it was Klipper's, after a
shutdown (devtools/simavr/fil_harness.c, watch_firmware_clock).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from devtools import simavr
from tests.fil.conftest import build_or_skip

PROGRAM = Path(__file__).resolve().parent / "avr" / "timer1_late_overflow.c"
PHASES = 48
TOV1, OCF1A = 0x01, 0x02


@pytest.fixture(scope="module")
def program(tmp_path_factory):
    build_or_skip()  # the simavr checkout and libelf, or a skip
    if not shutil.which("avr-gcc"):
        pytest.skip("no avr-gcc: the fil tier builds its firmware with it")
    elf = tmp_path_factory.mktemp("timer1") / "timer1_late_overflow.elf"
    subprocess.run(["avr-gcc", "-mmcu=atmega2560", "-Os", "-Wall", "-Werror",
                    "-o", str(elf), str(PROGRAM)], check=True)
    return elf


def test_a_late_overflow_still_matches_ocr1a_at_zero(program):
    names = ("after_nothing", "after_ocr1b", "after_ocr1a")
    results = simavr.run_program(program, *(
        (simavr.data_address(program, name), PHASES) for name in names))
    assert len(results) == len(names)
    missed = {name: [k for k, flags in enumerate(got)
                     if flags & (TOV1 | OCF1A) != TOV1 | OCF1A]
              for name, got in zip(names, results)}
    assert missed == {name: [] for name in names}, (
        "TIFR1 without TOV1|OCF1A ~30 cycles after the overflow, by phase: "
        + ", ".join(f"{name}: {[hex(results[i][k]) for k in ks]} at {ks}"
                    for i, (name, ks) in enumerate(missed.items()) if ks))
