"""`flowloop firmware`: Klipper's own make, on a copy of the checkout that
carries flowloop's EMS22 sensor command (flowloop.host.firmware)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..host import firmware, install
from .install import default_klipper


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "firmware", help="build and flash Klipper's MCU firmware with the EMS22"
                         " sensor command",
        description="Run Klipper's own make (menuconfig, a build, flash"
                    " FLASH_DEVICE=...) on a copy of the Klipper checkout that"
                    " carries flowloop's EMS22 sensor command; the checkout"
                    " itself is not changed (Moonraker can update it), its"
                    " .config and out/ are used as make uses them there. On"
                    " Kalico make runs in the checkout (flowloop's firmware"
                    " extra).")
    p.add_argument("--klipper", type=Path, default=None,
                   help="Klipper or Kalico checkout (default: $KLIPPER_PATH, else "
                        "~/klipper, else ~/kalico)")
    p.add_argument("--dry-run", action="store_true",
                   help="say where make would run, change nothing")
    p.add_argument("make_args", nargs=argparse.REMAINDER, metavar="MAKE_ARGUMENT",
                   help="what Klipper's make is given: menuconfig, nothing (a"
                        " build), flash FLASH_DEVICE=/dev/serial/by-id/..., clean;"
                        " make's own options after --")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.make_args[:1] == ["--"]:  # `flowloop firmware -- -j4`: make's options
        args.make_args = args.make_args[1:]
    klipper = args.klipper or default_klipper()
    source = install.source_tree()
    build = firmware.plan_build(klipper, source)
    if args.dry_run:
        print(f"would run {build.describe(args.make_args)}")
        return 0
    firmware.refresh_copy(build, source)
    print(f"running {build.describe(args.make_args)}", flush=True)
    code = firmware.run_make(build, args.make_args)
    if code != 0:
        print(f"make {' '.join(args.make_args)} failed (exit status {code}): its"
              " output is above", file=sys.stderr)
    return code
