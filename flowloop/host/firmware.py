"""Klipper's MCU firmware with flowloop's EMS22 command, built outside the
user's checkout so Moonraker's update manager keeps seeing it pristine.

`flowloop firmware ARGS` runs Klipper's own `make ARGS` in a copy of the
checkout refreshed on every run (a Klipper update is picked up) and patched
by flowloop.host.install.plan_firmware, the code the klippy tier of the tests
builds its firmware with. The copy holds only sources and is rebuilt each
time; what a user keeps stays where Klipper keeps it: `.config` and `out/` in
the checkout (both ignored by Klipper's .gitignore), so KIAUH, Katapult and
a later plain `make` find them as usual.

Kalico takes the EMS22 command as a firmware extra (src/extras/flowloop/,
ignored by Kalico's git): there `make` runs in the checkout itself.
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Dict, List, Optional

from . import install

# The one command that puts the EMS22 command back on an MCU.
FLASH_COMMAND = "flowloop firmware flash FLASH_DEVICE=<your MCU's serial>"
# Where `make menuconfig` shows the option (it is on by default where SPI is).
MENUS = {"Klipper": f"on small MCUs: '{install.LIMITED_MENU.split(chr(34))[1]}'",
         "Kalico": "'Firmware Extras'"}
OPTION = re.search(r'bool "([^"]+)"', install.KCONFIG_PROMPT).group(1)


def firmware_hint(host: str = "Klipper") -> str:
    """How to build and flash, as install and doctor say it."""
    menu = MENUS.get(host, MENUS["Klipper"])
    return (f"flowloop firmware menuconfig (your MCU as for {host}; {menu} ->"
            f" '{OPTION}' on, it is CONFIG_WANT_SENSOR_EMS22), then"
            f" {FLASH_COMMAND}")


# Not copied: git's data (the copy is no repository), what the build writes
# (kept in the checkout), the docs; lib/ (vendored SDKs, 200 MB) is linked.
SKIPPED = {".git", "out", ".config", ".config.old", "docs", "lib"}


def copy_root() -> Path:
    cache = os.environ.get("XDG_CACHE_HOME") or "~/.cache"
    return Path(cache).expanduser() / "flowloop" / "firmware"


@dataclasses.dataclass(frozen=True)
class Build:
    """Where make runs for a checkout, and what it is told."""
    klipper: Path
    folder: Path            # make's working folder: the copy, or Kalico itself
    copied: bool            # a patched copy (Klipper), else the checkout (Kalico)

    def argv(self, make_args: List[str]) -> List[str]:
        if not self.copied:
            return ["make", *make_args]
        return ["make", f"KCONFIG_CONFIG={self.klipper / '.config'}",
                f"OUT={self.klipper / 'out'}/", *make_args]

    def env(self) -> Dict[str, str]:
        # git must not find a repository around the copy: Klipper's build then
        # takes its version from klippy/.version, the checkout's.
        return dict(os.environ, GIT_CEILING_DIRECTORIES=str(self.folder.parent))

    def describe(self, make_args: List[str]) -> str:
        run = " ".join(["make", *make_args])
        if not self.copied:
            return f"{run} in {self.folder} (flowloop's firmware extra: src/extras)"
        return (f"{run} in {self.folder}, a copy of {self.klipper} with flowloop's"
                f" EMS22 sensor command; .config and out/ stay in {self.klipper}")


def plan_build(klipper: Path, source: Path, folder: Optional[Path] = None) -> Build:
    """Check that a build can be made; nothing is written."""
    klipper = Path(klipper).expanduser().resolve()
    install.check_klipper_tree(klipper)
    if not install.mcu_sources(source):
        raise install.InstallError(f"{source} carries no MCU sources (mcu_sensor/):"
                                   " reinstall flowloop")
    if shutil.which("make") is None:
        raise install.InstallError("no make on this machine: install Klipper's"
                                   " build tools (KIAUH does; or sudo apt install"
                                   " make gcc-arm-none-eabi ...)")
    if not os.access(klipper, os.W_OK):
        raise install.InstallError(f"{klipper}: not writable (its .config and out/"
                                   " are written)")
    if install.is_kalico(klipper):
        extra = klipper / "src" / "extras" / install.KALICO_EXTRA / "Kconfig"
        if not extra.is_file():
            raise install.InstallError(f"{extra.parent} is missing: run flowloop"
                                       " install first")
        return Build(klipper, klipper, copied=False)
    folder = folder or copy_root() / klipper.name
    return Build(klipper, Path(folder).expanduser(), copied=True)


def refresh_copy(build: Build, source: Path) -> None:
    """Copy the checkout as it is now and patch the copy; the old copy is
    replaced only once the new one is complete."""
    if not build.copied:
        return
    klipper, copy = build.klipper, build.folder
    copy.parent.mkdir(parents=True, exist_ok=True)
    tmp = copy.with_name(copy.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)

    def ignore(folder: str, names: List[str]) -> List[str]:
        top = Path(folder) == klipper
        return [n for n in names if (top and n in SKIPPED) or n == "__pycache__"
                or n.endswith(".pyc")]
    shutil.copytree(klipper, tmp, symlinks=True, ignore=ignore)
    if (klipper / "lib").is_dir():
        (tmp / "lib").symlink_to(klipper / "lib")
    version = git_describe(klipper)
    if version:
        (tmp / "klippy" / ".version").write_text(f"{version}-flowloop\n")
    install.apply(install.plan_firmware(tmp, source))
    shutil.rmtree(copy, ignore_errors=True)
    tmp.rename(copy)


def git_describe(tree: Path) -> Optional[str]:
    """The checkout's version as Klipper's build names it (`git describe
    --dirty`), read only: `describe --dirty` itself rewrites the index, so
    the dirty mark comes from `status` with --no-optional-locks."""
    describe = git(tree, "describe", "--always", "--tags", "--long")
    if not describe:
        return None
    modified = git(tree, "status", "--porcelain", "--untracked-files=no")
    return describe.strip() + ("-dirty" if modified and modified.strip() else "")


def git(tree: Path, *args: str) -> Optional[str]:
    """git on a user's checkout, read only: --no-optional-locks, so no index
    refresh is written while Moonraker's own git may run."""
    try:
        proc = subprocess.run(["git", "--no-optional-locks", "-C", str(tree), *args],
                              capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout if proc.returncode == 0 else None


def run_make(build: Build, make_args: List[str]) -> int:
    """Klipper's make, interactive (menuconfig) and with its own output."""
    return subprocess.run(build.argv(make_args), cwd=build.folder,
                          env=build.env()).returncode
