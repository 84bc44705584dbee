"""The oldest Klipper flowloop runs on: the sensor needs
mcu.register_serial_response (2026-02-26); no release has it, so the
installer refuses v0.13.0 and older with a message naming the minimum."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from flowloop.host import install

pytestmark = pytest.mark.unit

KLIPPER = Path("~/klipper").expanduser()


def _tree(tmp_path: Path, mcu_py: str) -> Path:
    tree = tmp_path / "klipper"
    (tree / "klippy" / "extras").mkdir(parents=True)
    (tree / "klippy" / "klippy.py").write_text("")
    (tree / "klippy" / "mcu.py").write_text(mcu_py)
    (tree / "src").mkdir()
    (tree / "src" / "Makefile").write_text("src-y += sched.c\n")
    (tree / "src" / "Kconfig").write_text(
        f"config WANT_SPI\n    bool\n{install.LIMITED_MENU}\nendmenu\n")
    return tree


def _release_mcu_py(tag: str) -> str:
    if not (KLIPPER / ".git").exists():
        pytest.skip("no Klipper checkout to read a release from")
    proc = subprocess.run(["git", "-C", str(KLIPPER), "show", f"{tag}:klippy/mcu.py"],
                          capture_output=True, text=True)
    if proc.returncode:
        pytest.skip(f"no {tag} in the Klipper checkout")
    return proc.stdout


def test_klipper_v0_13_0_is_refused_at_install_naming_the_minimum(tmp_path):
    tree = _tree(tmp_path, _release_mcu_py("v0.13.0"))
    source = Path(__file__).resolve().parents[2]
    with pytest.raises(install.InstallError) as e:
        install.plan_klipper(tree, source)
    assert "2026-02-26" in str(e.value) and "v0.13.0" in str(e.value)
    assert "git pull" in str(e.value)
    # uninstalling from an old Klipper still works
    install.plan_klipper(tree, source, uninstall=True)


def test_a_klipper_with_register_serial_response_is_accepted(tmp_path):
    mcu_py = "class MCU:\n    def register_serial_response(self, cb, msg):\n"
    tree = _tree(tmp_path, mcu_py)
    assert install.plan_klipper(tree, Path(__file__).resolve().parents[2])


def test_the_menuconfig_prompt_sits_with_klippers_sensor_chips(tmp_path):
    kconfig = KLIPPER / "src" / "Kconfig"
    if not kconfig.is_file():
        pytest.skip("no Klipper checkout")
    mcu_py = "class MCU:\n    def register_serial_response(self, cb, msg):\n"
    tree = _tree(tmp_path, mcu_py)
    (tree / "src" / "Kconfig").write_text(kconfig.read_text())
    install.apply(install.plan_firmware(tree, Path(__file__).resolve().parents[2]))
    text = (tree / "src" / "Kconfig").read_text()
    menu = text.index(install.LIMITED_MENU)
    prompt = text.index('bool "Support EMS22 filament flow sensor (flowloop)"')
    # in the small-flash menu, after Klipper's angle sensors, not under
    # "Other features"
    assert menu < text.index('bool "Support angle sensors"') < prompt
    assert prompt < text.index('comment "Other features"') < text.index("endmenu", menu)
