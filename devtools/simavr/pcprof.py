"""Where the AVR's cycles go, by firmware function: the simulated MCU with
klippy connected runs a sensor section (default: the EMS22 at 1 kHz) and
the same firmware without it; the harness counts cycles per instruction
address (`pcprof` on its control socket) and this names each address's
function from klipper.elf's symbols.

    .venv/bin/python -m devtools.simavr.pcprof [--rate 1000] [--angle]

Prints each function's cycles per sample, with the sensor minus without
(what a sample adds), largest first. A developer's tool: the bench
(tests/bench/bench_fil.py) gives the figures the goals are judged on.
"""

from __future__ import annotations

import argparse
import bisect
import collections
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Tuple

WARMUP_S, MEASURE_S = 1.5, 4.0


def symbols(elf: Path) -> Tuple[List[int], List[str]]:
    """Sorted start byte addresses of the text symbols, and their names."""
    out = subprocess.run(["avr-nm", "-n", str(elf)], capture_output=True,
                         text=True, check=True).stdout
    starts, names = [], []
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[1] in "tTwW":
            starts.append(int(parts[0], 16))
            names.append(parts[2])
    return starts, names


def by_function(dump: Path, starts: List[int], names: List[str],
                idle: Tuple[int, int]) -> Dict[str, int]:
    """Work cycles by function (the idle loop left out)."""
    cycles: Dict[str, int] = collections.Counter()
    for line in dump.read_text().splitlines():
        word, count = (int(v) for v in line.split())
        if idle[0] <= word * 2 < idle[1]:
            continue
        i = bisect.bisect_right(starts, word * 2) - 1
        cycles[names[i] if i >= 0 else "?"] += count
    return cycles


def profile(build, sections: str, angle: bool) -> Tuple[Dict[str, int], float]:
    """(cycles by function, simulated seconds) over MEASURE_S."""
    from devtools.klippy_api import KlippyApi
    from tests.fil.conftest import fil_printer
    with fil_printer(build, sections) as printer, \
            tempfile.TemporaryDirectory() as tmp:
        dump = Path(tmp) / "pcprof.txt"
        api = None
        if angle:   # [angle] samples only while a client reads its dump
            api = KlippyApi(printer.klippy.api_socket)
            api.send("angle/dump_angle", sensor="bench", response_template={})
        try:
            time.sleep(WARMUP_S)
            printer.sim.control("pcprof on")
            s0 = float(printer.sim.status()["sim_s"])
            time.sleep(MEASURE_S)
            printer.sim.control(f"pcprof dump {dump}")
            s1 = float(printer.sim.status()["sim_s"])
        finally:
            if api is not None:
                api.close()
        from devtools import simavr
        elf = build.elf("atmega2560")
        starts, names = symbols(elf)
        return by_function(dump, starts, names, simavr.idle_loop(elf)), s1 - s0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--angle", action="store_true",
                        help="Klipper's [angle] as5047d instead of the EMS22")
    parser.add_argument("--top", type=int, default=25)
    args = parser.parse_args(argv)
    from tests.bench.bench_fil import ANGLE, EMS22
    from tests.fil.conftest import build_or_skip
    build = build_or_skip()
    section = (ANGLE if args.angle else EMS22).format(period=1.0 / args.rate)
    with_sensor, seconds = profile(build, section, args.angle)
    without, seconds0 = profile(build, "", False)
    samples = args.rate * seconds
    rows = []
    for name in set(with_sensor) | set(without):
        added = with_sensor.get(name, 0) - without.get(name, 0) * seconds / seconds0
        rows.append((added / samples, name))
    rows.sort(reverse=True)
    total = sum(r[0] for r in rows)
    print(f"{'cycles/sample':>14}  function   ({args.rate:g} Hz, "
          f"{'angle' if args.angle else 'ems22'}, {samples:.0f} samples)")
    for per, name in rows[:args.top]:
        print(f"{per:14.1f}  {name}")
    print(f"{total:14.1f}  total added")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
