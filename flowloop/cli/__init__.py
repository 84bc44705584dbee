"""The `flowloop` command: one subcommand per job, each defined beside its code.

Each module listed here has register(subparsers), which adds its parser and
sets func(args) -> exit code. A FlowloopError becomes one line on stderr and
exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
from typing import List, Optional

from .. import __version__
from ..errors import FlowloopError

# Each command and the module that defines it. `flowloop COMMAND` imports only
# that module: a start-up cost Moonraker pays per upload for `annotate`.
COMMANDS = {
    "install": "flowloop.cli.install",
    "info": "flowloop.cli.info",
    "doctor": "flowloop.cli.doctor",
    "firmware": "flowloop.cli.firmware",
    "ab-calibrate": "flowloop.cli.diff_ab",
    "ab-pylons": "flowloop.cli.diff_ab",
    "profile": "flowloop.cli.profile",
    "delta-endstops": "flowloop.cli.delta",
    "annotate": "flowloop.cli.annotate",
    "measure-part": "flowloop.cli.measure",
    "report": "flowloop.cli.report",
}
COMMAND_MODULES = tuple(dict.fromkeys(COMMANDS.values()))


_UNSIGNED = r"(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|inf|nan"
# A negative number, or a list of numbers starting with one: "-86.6,-50,0.3",
# "-1e-3", "-150.1 150.2". Such a word is an option's value, never an option.
SIGNED_VALUE = re.compile(rf"^-(?:{_UNSIGNED})(?:[,\s]+[-+]?(?:{_UNSIGNED}))*,?$",
                          re.IGNORECASE)


class ArgumentParser(argparse.ArgumentParser):
    """argparse that takes `--probe -86.6,-50,0.3` as it is typed.

    argparse only lets a plain negative number ("-5", "-0.5") follow an
    option; anything else starting with '-' is taken for an option and
    fails with "expected one argument". Every flowloop parser is this class
    (subparsers inherit their parent's class), so coordinates and signed
    lists work for every option of every command.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # argparse's own hook for this: the pattern of "looks like a negative number".
        self._negative_number_matcher = SIGNED_VALUE

    def parse_known_args(self, args=None, namespace=None):
        # The innermost (sub)command refuses what it does not know, so the
        # usage and message are its own ("flowloop annotate"), not the top's.
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(self._unknown(extras))
        return namespace, extras

    def _unknown(self, extras: List[str]) -> str:
        option = next((e for e in extras if e.startswith("-")), None)
        if option is None:
            return f"unrecognized arguments: {' '.join(extras)}"
        # imported here: only a mistyped option needs it
        import difflib
        option = option.split("=", 1)[0]
        known = [o for action in self._actions for o in action.option_strings]
        close = difflib.get_close_matches(option, known, n=1)
        return f"unknown option {option}" + (f" (did you mean {close[0]}?)"
                                             if close else "")


def build_parser(command: Optional[str] = None) -> argparse.ArgumentParser:
    """The whole parser, or (command given) one with that command only."""
    parser = ArgumentParser(
        prog="flowloop",
        description="Closed-loop extrusion and precision calibration for Klipper.")
    parser.add_argument("--version", action="version",
                        version=f"flowloop {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    modules = (COMMANDS[command],) if command in COMMANDS else COMMAND_MODULES
    for name in modules:
        importlib.import_module(name).register(sub)
    return parser


def _one_file_process() -> None:
    """Settings for a process that annotates one file and ends (Moonraker's
    processor runs one per upload), made before numpy is imported."""
    # the BLAS threads numpy starts at import would only spin: the
    # annotator does no linear algebra
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    # The planner's arrays of a chunk are some hundred kB each: glibc's
    # malloc maps each from the kernel and unmaps it when freed, and the
    # next one is faulted in again page by page (39,000 page faults for a
    # 25 MB file, 11,000 without, some 0.04 s of system time). Kept in the
    # heap, freed ones are reused.
    try:
        import ctypes
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):   # not glibc: as it is
        return
    mallopt(-3, 32 << 20)       # M_MMAP_THRESHOLD: map only blocks over 32 MB
    mallopt(-1, 128 << 20)      # M_TRIM_THRESHOLD: keep up to 128 MB freed


def main(argv: Optional[List[str]] = None) -> int:
    one_file = False
    if argv is None:
        argv = sys.argv[1:]
        one_file = argv[:1] == ["annotate"]
        if one_file:
            _one_file_process()
    parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)
    try:
        code = args.func(args) or 0
    except FlowloopError as e:
        print(f"flowloop {args.command}: error: {e}", file=sys.stderr)
        code = 2
    if one_file:
        # The process ends with the command (its files are closed): without
        # the interpreter's teardown of numpy and the rest, 15 ms of a 25 MB
        # file's 0.5 s
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
