"""`flowloop install`: link flowloop into the user's Klipper and Moonraker."""

from __future__ import annotations

import os
from pathlib import Path
from typing import List

from ..host.firmware import firmware_hint
from ..host.install import (
    Change,
    InstallError,
    apply,
    check_all,
    host_name,
    is_checkout,
    mcu_sources,
    plan_klipper,
    plan_moonraker,
    plan_moonraker_conf,
    plan_printer_cfg,
    source_tree,
)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "install", help="link flowloop into Klipper and Moonraker",
        description="Link flowloop's klippy modules and Moonraker component into "
                    "the user's trees (no file git tracks is changed), add [flowloop] "
                    "to moonraker.conf. Idempotent; --uninstall restores every file "
                    "as it was and comments flowloop's sections in printer.cfg out.")
    home = Path("~")
    p.add_argument("--klipper", type=Path, default=None,
                   help="Klipper or Kalico checkout (default: $KLIPPER_PATH, else "
                        "~/klipper, else ~/kalico)")
    p.add_argument("--moonraker", type=Path, default=None,
                   help="Moonraker checkout or virtualenv (default: ~/moonraker, "
                        "else ~/moonraker-env)")
    p.add_argument("--config-dir", type=Path, default=home / "printer_data" / "config",
                   help="folder with moonraker.conf and printer.cfg (default:"
                        " ~/printer_data/config)")
    p.add_argument("--no-moonraker", action="store_true",
                   help="only patch Klipper")
    p.add_argument("--dry-run", action="store_true", help="print what would change")
    p.add_argument("--uninstall", action="store_true", help="take flowloop out again")
    p.set_defaults(func=run)


def _default_moonraker() -> Path:
    for candidate in (Path("~/moonraker"), Path("~/moonraker-env")):
        if candidate.expanduser().exists():
            return candidate
    raise InstallError("no Moonraker at ~/moonraker or ~/moonraker-env; "
                       "pass --moonraker or --no-moonraker")


def default_klipper() -> Path:
    """$KLIPPER_PATH, else ~/klipper, else ~/kalico (where KIAUH puts it)."""
    if os.environ.get("KLIPPER_PATH"):
        return Path(os.environ["KLIPPER_PATH"])
    for candidate in (Path("~/klipper"), Path("~/kalico")):
        if candidate.expanduser().exists():
            return candidate
    return Path("~/klipper")


def plan(args, source: Path) -> List[Change]:
    if args.klipper is None:
        args.klipper = default_klipper()
    changes = plan_klipper(args.klipper, source, args.uninstall)
    changes += plan_printer_cfg(args.config_dir, source, args.uninstall)
    if not args.no_moonraker:
        moonraker = args.moonraker or _default_moonraker()
        changes += plan_moonraker(moonraker, source, args.uninstall)
        changes += plan_moonraker_conf(args.config_dir, source, args.uninstall)
    return changes


def run(args) -> int:
    source = source_tree()
    changes = plan(args, source)
    notes = [change.what for change in changes if change.note]
    changes = [change for change in changes if not change.note]
    for note in notes:
        print(note)
    if not changes:
        print("nothing to do: " + ("flowloop is not installed" if args.uninstall
                                   else "flowloop is installed"))
        return 0
    if args.dry_run:
        check_all(changes)
        for change in changes:
            print(f"would {change.what}")
        return 0
    apply(changes)  # checks everything first; prints only what was done
    for change in changes:
        print(change.what)
    host = host_name(args.klipper)
    if not args.uninstall and mcu_sources(source):
        print(f"MCU: build and flash {host}'s firmware with the EMS22 sensor"
              f" command: {firmware_hint(host)}")
    if not args.uninstall and not args.no_moonraker and not is_checkout(source):
        print("flowloop runs from a pip install: update it with pip install "
              "-U klipper-flowloop, then run flowloop install again")
    restart = host.lower() if args.no_moonraker else f"{host.lower()} and moonraker"
    print(f"restart {restart} to load the change")
    return 0
