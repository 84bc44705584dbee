"""The `flowloop` command: one subcommand per job, each defined beside its code.

Each module listed here has register(subparsers), which adds its parser and
sets func(args) -> exit code. A FlowloopError becomes one line on stderr and
exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import List, Optional

from .. import __version__
from ..errors import FlowloopError

COMMAND_MODULES = (
    "flowloop.cli.install",
    "flowloop.cli.info",
    "flowloop.cli.diff_ab",
    "flowloop.cli.profile",
    "flowloop.cli.delta",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="flowloop",
        description="Closed-loop extrusion and precision calibration for Klipper.")
    parser.add_argument("--version", action="version",
                        version=f"flowloop {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args) or 0
    except FlowloopError as e:
        print(f"flowloop {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
