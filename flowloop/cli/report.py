"""`flowloop report`: a print's flow report, from a stored dump, as one HTML file."""

from __future__ import annotations

from pathlib import Path

from ..errors import FlowloopError
from ..report import dump, render


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help="render a print's flow report (HTML) from its dump",
        description="Render the flow report of a print from the dump Moonraker "
                    "stored for its job (data path flowloop/reports/JOB.json): "
                    "one HTML file with inline SVG that opens offline "
                    "(docs/flow_report.md).")
    p.add_argument("dump", type=Path, metavar="DUMP.json", help="the report's dump")
    p.add_argument("-o", "--output", type=Path, metavar="REPORT.html",
                   help="the HTML file to write (DUMP.json with .html)")
    p.set_defaults(func=run)


def run(args) -> int:
    output = args.output or args.dump.with_suffix(".html")
    if output.exists() and args.dump.exists() and output.samefile(args.dump):
        raise FlowloopError(f"{output} is the dump itself: give another -o")
    rec = dump.load(args.dump)
    try:
        dump.save(output, render.html(rec))
    except OSError as e:
        raise FlowloopError(f"{output}: cannot write: {e.strerror or e}") from None
    print(f"wrote {output}")
    for label, value in render.summary_rows(rec):
        print(f"  {label}: {value}")
    for text in rec.lacks():
        print(f"  lacks: {text}")
    return 0
