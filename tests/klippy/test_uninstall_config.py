"""`flowloop install --uninstall` leaves a printer.cfg klippy starts with
(issue 35): run on the klippy of the host without flowloop's modules, the
printer's configuration with every flowloop section (in printer.cfg, in an
included file and in the SAVE_CONFIG block) stops klippy before the uninstall
and starts it after; the next install gives the files back byte for byte."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from devtools import stack
from flowloop.host import install

HERE = Path(__file__).resolve().parent

PRINTER_CFG = """\
{printer}
[include flowloop/*.cfg]

[heater_bed]
heater_pin: PH5
sensor_type: EPCOS 100K B57560G104F
sensor_pin: PK6
control: watermark
min_temp: 0
max_temp: 110

#*# <---------------------- SAVE_CONFIG ---------------------->
#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.
#*#
#*# [flow_sensor_simulation sim]
#*# heater_power = 40
#*#
#*# [extruder]
#*# pid_kp = 22.200
"""

FLOWLOOP_CFG = """\
[flowloop]

[flow_sensor_simulation sim]

[flowrate_limiter]
max_flow: 8

[autotemp]

[measure_profile]
step_time: 3

[diff_ab_calibrate]
equilibrium_window: 5
"""


def _without_flowloop(build, folder: Path) -> Path:
    """A copy of the host's klippy without flowloop's modules (its extras
    links into this checkout left out): klippy as it is after uninstall."""
    def ignore(path, names):
        return [n for n in names
                if os.path.islink(os.path.join(path, n))
                and stack.PROJECT in Path(os.path.join(path, n)).resolve().parents]
    shutil.copytree(build.tree / "klippy", folder / "klippy", symlinks=True,
                    ignore=ignore)
    assert not (folder / "klippy" / "extras" / "flowrate_limiter.py").exists()
    return folder / "klippy" / "klippy.py"


def _start(venv, klippy: Path, config: Path, build, folder: Path):
    gcode = folder / "empty.gcode"
    gcode.write_text("")
    log = folder / "klippy.log"
    log.unlink(missing_ok=True)
    proc = subprocess.run(
        [str(venv.python), str(klippy), str(config), "-i", str(gcode),
         "-o", str(folder / "out"), "-l", str(log),
         "-d", str(build.dictionary("atmega2560"))],
        cwd=folder, capture_output=True, text=True, timeout=120)
    text = (log.read_text(errors="replace") if log.exists() else "") + proc.stderr
    return proc.returncode, text


def test_uninstall_leaves_a_printer_cfg_klippy_starts_with(klipper_build,
                                                          klippy_venv, tmp_path):
    config_dir = tmp_path / "config"
    (config_dir / "flowloop").mkdir(parents=True)
    printer = (HERE / "flow_sensor_printer.cfg").read_text()
    main = config_dir / "printer.cfg"
    main.write_text(PRINTER_CFG.format(printer=printer))
    included = config_dir / "flowloop" / "sections.cfg"
    # an included file with Windows line endings, as an editor may leave it
    included.write_bytes(FLOWLOOP_CFG.replace("\n", "\r\n").encode())
    before = {p: p.read_bytes() for p in (main, included)}
    klippy = _without_flowloop(klipper_build, tmp_path)

    code, log = _start(klippy_venv, klippy, main, klipper_build, tmp_path)
    assert code != 0 and "is not a valid config section" in log, log[-2000:]

    install.apply(install.plan_printer_cfg(config_dir, stack.PROJECT,
                                           uninstall=True))
    assert main.read_bytes() != before[main]
    assert included.read_bytes() != before[included]
    code, log = _start(klippy_venv, klippy, main, klipper_build, tmp_path)
    assert code == 0, log[-3000:]
    assert "is not a valid config section" not in log
    # the SAVE_CONFIG block's flowloop section is commented out inside it,
    # its other sections kept as SAVE_CONFIG wrote them
    text = main.read_text()
    assert ("#*# #[flow_sensor_simulation sim]" in text
            and "#*# [flow_sensor_simulation sim]" not in text)
    assert "#*# [extruder]\n#*# pid_kp = 22.200" in text

    install.apply(install.plan_printer_cfg(config_dir, stack.PROJECT))
    assert {p: p.read_bytes() for p in (main, included)} == before
