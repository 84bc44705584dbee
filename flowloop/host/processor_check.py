"""The upload annotator as Moonraker runs it, and a check that it works.

Moonraker's metadata script runs a registered G-code processor with
`subprocess.run(arglist, capture_output=True, timeout=...)` (metadata.py
run_gcode_processors): the argument `{gcode_file_path}` replaced by the file,
no shell, the environment and working directory Moonraker was started with. A
failure is only logged, so an upload that is not annotated says nothing.

The command is `python -P -m flowloop annotate ...` (`-I` before Python
3.11, which has no -P): with `-m` alone the working directory comes first on
sys.path, and a folder named flowloop/ there (a home holding the clone) is
imported instead of the installed package.

`check_processor` runs a command on a tiny G-code file the same way and
answers None when the file comes back annotated, else one line saying why not
(`flowloop doctor` asks Moonraker to run it: POST
/server/flowloop/annotation/check).
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import List, Optional, Sequence, Union

FILE_ARG = "{gcode_file_path}"
CHECK_TIMEOUT_S = 60.0
# Enough to plan: a homed printer, a wait, a few extruding moves.
TINY_GCODE = """\
; flowloop processor check
G28
G90
M83
G1 Z0.2 F600
G1 X10 Y10 F6000
G1 X60 Y10 E2.5 F1800
G1 X60 Y60 E2.5
G1 X10 Y60 E2.5
G1 X10 Y10 E2.5
"""


def isolation_flag(version=sys.version_info) -> str:
    """The interpreter option that keeps the working directory off sys.path:
    -P (3.11+), else -I (isolated: also ignores PYTHON* variables and the user's
    site-packages, which a virtualenv does not use)."""
    return "-P" if version >= (3, 11) else "-I"


def processor_command(python: str, printer_cfg: Optional[str] = None
                      ) -> List[str]:
    """The annotator's command line for Moonraker: python's flowloop, immune
    to the working directory, the file annotated in place."""
    cmd = [python, isolation_flag(), "-m", "flowloop", "annotate"]
    if printer_cfg:
        cmd += ["--printer-cfg", printer_cfg]
    return cmd + [FILE_ARG]


def moonraker_arglist(command: Union[str, Sequence[str]], path: str) -> List[str]:
    """A processor's command as Moonraker's metadata script turns it into
    arguments: a string is split as a shell would, FILE_ARG is the file."""
    args = shlex.split(command) if isinstance(command, str) else list(command)
    return [path if arg == FILE_ARG else arg for arg in args]


def check_processor(command: Union[str, Sequence[str]],
                    timeout_s: float = CHECK_TIMEOUT_S,
                    cwd: Optional[str] = None) -> Optional[str]:
    """Run command on a tiny G-code file as Moonraker does (cwd None: this
    process's working directory, as Moonraker's processors inherit its own).
    None when the file comes back annotated; else one line saying why not."""
    from ..gcode.annotate import HEADER_BYTES, is_annotated
    where = os.path.abspath(cwd or os.getcwd())
    with tempfile.TemporaryDirectory(prefix="flowloop-check-") as tmp:
        path = Path(tmp) / "flowloop-check.gcode"
        path.write_text(TINY_GCODE)
        try:
            proc = subprocess.run(moonraker_arglist(command, str(path)),
                                  capture_output=True, timeout=timeout_s, cwd=cwd)
        except subprocess.TimeoutExpired:
            return f"the G-code processor ran over {timeout_s:g} s on a 10-line file"
        except OSError as e:
            return f"the G-code processor cannot start: {e.strerror}: {e.filename}"
        if proc.returncode != 0:
            return (f"the G-code processor fails (exit {proc.returncode}) run from"
                    f" {where}: {last_line(proc.stderr or proc.stdout)}"
                    + shadow_hint(where))
        with open(path, "rb") as f:
            if not is_annotated(f.read(HEADER_BYTES)):
                return ("the G-code processor exits 0 but leaves the file"
                        " unannotated: it is not flowloop annotate")
    return None


def last_line(output: bytes) -> str:
    """The last non-blank line of a process's output (a traceback's error)."""
    lines = [ln.strip() for ln in output.decode(errors="replace").splitlines()]
    lines = [ln for ln in lines if ln]
    return lines[-1] if lines else "no output"


def shadow_hint(cwd: str) -> str:
    """Why `-m flowloop` may import the wrong package there."""
    if os.path.isdir(os.path.join(cwd, "flowloop")):
        return (f" (a folder named flowloop/ in {cwd} is imported instead of"
                f" the installed package: update flowloop)")
    return ""
