"""`flowloop info`: ask a running Moonraker what flowloop has loaded."""

from __future__ import annotations

import json

from .. import __version__
from ..host.info import describe, fetch_info


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "info", help="show what flowloop has loaded in a running Moonraker/klippy",
        description=f"flowloop {__version__}: query GET /server/flowloop/info.")
    p.add_argument("--moonraker", default="http://127.0.0.1:7125",
                   help="Moonraker URL (default: http://127.0.0.1:7125)")
    p.add_argument("--json", action="store_true", help="print the raw JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    info = fetch_info(args.moonraker)
    print(json.dumps(info, indent=2) if args.json
          else describe(info, args.moonraker))
    return 0
