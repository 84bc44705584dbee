"""Run a klippy batch-mode regression file (*.test) against a KlipperBuild.

The file format is Klipper's own (scripts/test_klippy.py): CONFIG, DICTIONARY,
GCODE and SHOULD_FAIL directives, every other line is G-code; '#' starts a
comment. Several CONFIG lines make several runs, each with the G-code read
so far. This is our own runner so that a run can be judged on its log too:
an "Unknown command" anywhere in the log fails the run, and a comment line
"# EXPECT_LOG: text" (a comment, so Klipper's own runner ignores it) requires
that text in the log of every run of the file: a SHOULD_FAIL test says why
it must fail. "# EXPECT_NO_LOG: text" requires that text in no run's log
(a refusal that changed nothing: "# EXPECT_NO_LOG: save_config: set").
write_test writes a .test file (and its printer config) for a test that
makes one up.
"""

from __future__ import annotations

import dataclasses
import subprocess
from pathlib import Path
from typing import List, Optional, Tuple, Union

from .stack import REALTIME_KLIPPY, KlipperBuild, Venv

EXPECT_LOG = "# EXPECT_LOG:"
EXPECT_NO_LOG = "# EXPECT_NO_LOG:"


class KlippyTestFailure(Exception):
    pass


@dataclasses.dataclass
class Run:
    config: Path
    dictionaries: List[str]
    gcode: List[str]
    gcode_file: Optional[Path]
    should_fail: bool
    expect_log: List[str] = dataclasses.field(default_factory=list)
    expect_no_log: List[str] = dataclasses.field(default_factory=list)


def parse(test_file: Path, dict_dir: Path) -> List[Run]:
    here = Path(test_file).resolve().parent
    config = gcode_file = None
    dictionaries: List[str] = []
    should_fail = multi = False
    gcode: List[str] = []
    runs: List[Run] = []
    expect_log: List[str] = []
    expect_no_log: List[str] = []

    def launch(cfg: Path) -> None:
        runs.append(Run(cfg, list(dictionaries), list(gcode), gcode_file, should_fail))

    for raw in test_file.read_text().splitlines():
        if raw.strip().startswith(EXPECT_LOG):
            expect_log.append(raw.strip()[len(EXPECT_LOG):].strip())
            continue
        if raw.strip().startswith(EXPECT_NO_LOG):
            expect_no_log.append(raw.strip()[len(EXPECT_NO_LOG):].strip())
            continue
        line = raw.split("#", 1)[0].strip()
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "CONFIG":
            if config is not None and not multi:
                multi = True
                launch(config)
            config = here / parts[1]
            if multi:
                launch(config)
        elif parts[0] == "DICTIONARY":
            dictionaries = [str(dict_dir / parts[1])]
            for extra in parts[2:]:
                mcu, fname = extra.split("=", 1)
                dictionaries.append(f"{mcu.strip()}={dict_dir / fname.strip()}")
        elif parts[0] == "GCODE":
            gcode_file = here / parts[1]
        elif parts[0] == "SHOULD_FAIL":
            should_fail = True
        else:
            gcode.append(line)
    if not multi:
        if config is None:
            raise KlippyTestFailure(f"{test_file}: no CONFIG line")
        launch(config)
    for run in runs:
        run.expect_log = list(expect_log)
        run.expect_no_log = list(expect_no_log)
    return runs


def write_test(folder: Path, name: str, gcode: str = "", *,
               cfg: Optional[str] = None, config: Optional[Path] = None,
               dictionary: Union[str, Path] = "atmega2560.dict",
               should_fail: bool = False) -> Tuple[Path, Path]:
    """Write folder/NAME.test: DICTIONARY, CONFIG, SHOULD_FAIL if asked,
    then gcode (G-code and directives, as in a .test file). The printer
    config is cfg, its text, written to folder/NAME.cfg, or config, an
    existing file (exactly one of them). Returns (config, test) paths."""
    if (cfg is None) == (config is None):
        raise ValueError("write_test: give cfg (a config's text) or config "
                         "(a config file), not both or neither")
    if cfg is not None:
        config = Path(folder) / f"{name}.cfg"
        config.write_text(cfg)
    test = Path(folder) / f"{name}.test"
    test.write_text(f"DICTIONARY {dictionary}\nCONFIG {config}\n"
                    + ("SHOULD_FAIL\n" if should_fail else "") + gcode)
    return Path(config), test


def run_file(test_file: Path, build: KlipperBuild, venv: Venv, workdir: Path,
             allow_unknown: bool = False) -> str:
    """Run every run of a .test file; return the logs, raise on failure.

    allow_unknown is only for Klipper's own files, which send some commands
    their configs lack (commands.test sends M206) and judge on exit code alone.
    """
    logs = []
    for i, run in enumerate(parse(Path(test_file), build.dict_dir)):
        if not run.dictionaries:
            raise KlippyTestFailure(f"{test_file}: no DICTIONARY line")
        if run.gcode_file is not None and run.gcode:
            raise KlippyTestFailure(f"{test_file}: both GCODE and G-code lines")
        gcode_file = run.gcode_file
        if gcode_file is None:
            gcode_file = workdir / f"run{i}.gcode"
            gcode_file.write_text("\n".join(run.gcode + [""]))
        log_file = workdir / f"run{i}.log"
        # Klipper's own klippy runs through the launcher that waits for the
        # output to be written before exit (realtime_klippy.py --no-pace); a
        # test's harness script runs as it is
        own = Path(build.klippy) == Path(build.tree) / "klippy" / "klippy.py"
        launcher = [str(REALTIME_KLIPPY), "--no-pace"] if own else []
        cmd = [str(venv.python)] + launcher + [str(build.klippy), str(run.config),
               "-i", str(gcode_file), "-o", str(workdir / f"run{i}.output"),
               "-l", str(log_file), "-v"]
        for d in run.dictionaries:
            cmd += ["-d", d]
        proc = subprocess.run(cmd, cwd=build.tree, capture_output=True, text=True,
                              timeout=600)
        log = log_file.read_text(errors="replace") if log_file.exists() else ""
        log += proc.stdout + proc.stderr
        logs.append(log)
        where = f"{Path(test_file).name} ({run.config.name})"
        if run.should_fail and proc.returncode == 0:
            raise KlippyTestFailure(f"{where}: expected klippy to fail, it did not\n"
                                    + _tail(log))
        if not run.should_fail and proc.returncode != 0:
            raise KlippyTestFailure(f"{where}: klippy failed ({proc.returncode})\n"
                                    + _tail(log))
        missing = [text for text in run.expect_log if text not in log]
        if missing:
            raise KlippyTestFailure(f"{where}: log lacks {missing[0]!r}\n"
                                    + _tail(log))
        unwanted = [text for text in run.expect_no_log if text in log]
        if unwanted:
            raise KlippyTestFailure(f"{where}: log has {unwanted[0]!r}\n"
                                    + _tail(log))
        unknown = [ln for ln in log.splitlines() if "Unknown command" in ln]
        if unknown and not allow_unknown:
            raise KlippyTestFailure(f"{where}: {unknown[0].strip()}\n" + _tail(log))
    return "\n".join(logs)


def _tail(log: str, chars: int = 6000) -> str:
    return log[-chars:]
