"""`make demo`: start the local stack and show what flowloop does.

Starts a batch-mode klippy with config/printer.cfg and Moonraker with the
flowloop component, both on 127.0.0.1, prints the Moonraker URL and what
flowloop has loaded, then runs each feature's demo step (devtools/demo_*.py,
each a `demo(ctx)` function). Ctrl-C stops everything. Without a Klipper
checkout it says so and runs Moonraker alone, and the steps run offline.

What it keeps: by default nothing. Its data directory (Moonraker's database
with the profiles stored, G-code files, logs) is a new temporary one removed
when the demo stops, and the port is new on every run. With
FLOWLOOP_DEMO_DATA=DIR (or --data-dir DIR) the data directory is DIR: created
if missing, kept when the demo stops, and used again by the next run (the
config files in it are rewritten on every start, the database is not).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import shutil
import signal
import sys
import traceback
from pathlib import Path
from typing import Optional

from devtools import stack
from flowloop.host.info import describe

DATA_ENV = "FLOWLOOP_DEMO_DATA"


class DemoContext:
    def __init__(self, printer: Optional[stack.PrinterStack],
                 kept: Optional[contextlib.ExitStack] = None):
        self.printer = printer
        self.project = stack.PROJECT
        self.kept = kept or contextlib.ExitStack()
        self.live_page_url: Optional[str] = None   # set by the live step

    def keep(self, context):
        """Enter a context (another stack, for the live step) that stays up
        until the demo stops; its value."""
        return self.kept.enter_context(context)

    @property
    def moonraker(self) -> Optional[stack.Moonraker]:
        return self.printer.moonraker if self.printer else None

    @property
    def klippy_available(self) -> bool:
        return bool(self.printer and self.printer.klippy)

    def say(self, text: str = "") -> None:
        print(text, flush=True)

    def gcode(self, script: str) -> str:
        return self.printer.gcode(script)

    def query(self, obj: str) -> dict:
        return self.printer.query(obj)

    def query_many(self, *objects: str) -> dict:
        return self.printer.query_many(*objects)

    def batch_klippy_log(self, test_file: Path) -> str:
        """Run a tests/klippy .test file in batch mode; return klippy's log."""
        from devtools.klippy_test import run_file
        workdir = stack.short_tempdir("fl-demo-")
        try:
            return run_file(test_file, stack.build_klipper(), stack.klippy_venv(),
                            workdir)
        finally:
            shutil.rmtree(workdir, ignore_errors=True)


def demo_steps():
    for path in sorted(Path(__file__).parent.glob("demo_*.py")):
        yield path.stem[len("demo_"):], importlib.import_module(f"devtools.{path.stem}")


def run_steps(ctx: DemoContext, only: Optional[str] = None) -> int:
    failed = 0
    for name, module in demo_steps():
        if only and name != only:
            continue
        ctx.say(f"\n=== {name.replace('_', ' ')} ===")
        try:
            module.demo(ctx)
        except Exception:  # a broken step is reported, the others still run
            failed += 1
            ctx.say(f"!!! demo step {name} failed:\n{traceback.format_exc()}")
    return failed


def _stop_on_signals() -> None:
    """Ctrl-C (and a plain kill) end the demo through its cleanup, even when
    started from a shell that made SIGINT ignored for background jobs."""
    def stop(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="make demo",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--once", action="store_true",
                        help="stop after the steps instead of waiting for Ctrl-C")
    parser.add_argument("--step", choices=[name for name, _ in demo_steps()],
                        help="run only this feature's step")
    parser.add_argument("--data-dir", type=Path,
                        default=os.environ.get(DATA_ENV) or None,
                        help=f"keep the data directory here and use it again on the "
                             f"next run (default: ${DATA_ENV}, else a temporary one "
                             f"removed at the end)")
    args = parser.parse_args(argv)
    stack.cache_bytecode()   # klippy and Moonraker start faster
    data_dir = args.data_dir.expanduser().resolve() if args.data_dir else None
    if data_dir is not None:
        data_dir.mkdir(parents=True, exist_ok=True)
    _stop_on_signals()
    reason = stack.missing_klipper_reason()
    if reason:
        print("!!! " + reason, flush=True)
        print("!!! The demo runs Moonraker alone; steps show what works offline.",
              flush=True)
    print("Starting the local stack (first run builds Klipper and two "
          "virtualenvs: a few minutes)...", flush=True)
    with stack.printer_stack(with_klippy=reason is None,
                             data_dir=data_dir) as printer, \
            contextlib.ExitStack() as kept:
        status, body = printer.moonraker.request("GET", "/server/flowloop/info")
        print(f"\nMoonraker: {printer.moonraker.url}  (data: {printer.data_dir})")
        print("  data directory " + (
            "kept when the demo stops and used again by the next run"
            if data_dir else f"removed when the demo stops (set {DATA_ENV}=DIR "
                             f"or --data-dir DIR to keep it)"))
        print(f"  GET {printer.moonraker.url}/server/flowloop/info")
        print("  " + describe(body["result"], printer.moonraker.url).replace(
            "\n", "\n  "))
        ctx = DemoContext(printer, kept)
        failed = run_steps(ctx, args.step)
        if failed:
            print(f"\n!!! {failed} demo step(s) failed (see above)")
        print(f"\nCheck it as a user would: flowloop doctor --moonraker"
              f" {printer.moonraker.url}", flush=True)
        if ctx.live_page_url:
            print(f"Live page: {ctx.live_page_url}", flush=True)
        if not args.once:
            print(f"\nThe stack is running at {printer.moonraker.url}. "
                  f"Ctrl-C stops everything.", flush=True)
            try:
                signal.pause()
            except KeyboardInterrupt:
                print("\nstopping klippy and Moonraker...", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # while starting: the stack has cleaned up
        print("\nstopped", flush=True)
        sys.exit(130)
