"""`flowloop annotate` against preprocess_cancellation, as whole processes.

preprocess_cancellation is the G-code processor Moonraker ships (its
`check_objects` option runs it on every upload); `flowloop annotate` is meant
to run in the same place. Moonraker's metadata script, a process per upload,
runs flowloop's command as a process of its own but preprocess_cancellation
inside itself (docs/autotemp.md, "Speed"), so the pair below leaves a Python
start-up (about 0.01 s) in preprocess_cancellation's time that Moonraker does
not pay. Both are timed here as whole processes, start-up included:
`python -m flowloop annotate FILE` (the command line of flowloop's Moonraker
processor) and `python -m preprocess_cancellation FILE`, each rewriting a
fresh copy of the same file in place, alternately, ROUNDS (5) times; the
median of each counts, and the figure is flowloop's wall time as a ratio of
preprocess_cancellation's (goal: <= 1.0x), and their CPU times likewise.

The file is about 25 MB: the shared data's `parts.gcode` (FLOWLOOP_BENCH_GCODE)
four times over when it is there, else the shipped excerpt
tests/data/gcode/block_layers_1_2.gcode's layers again and again (each after
a `G92 E0`), as a long print is. Neither carries object labels, so
preprocess_cancellation only scans it and copies it (its lightest case). The
same file is timed again labelled the way PrusaSlicer labels objects
(`--gcode-label-objects`: each layer's moves between `; printing object ...`
and `; stop printing object ...`), the case preprocess_cancellation exists for
(it then reads every extruding move of an object for its outline; on a real
PrusaSlicer 2.5 file of three labelled objects, 24 MB, it took as long per MB
as on this one). Start-up alone is the same two commands on the 22 kB excerpt; "without
start-up" subtracts it. "planner alone" is flowloop.gcode.bulk_planner in this
process, without the annotation, against the same whole-process figure.

Both run with their bytecode cached, as installed packages do (pip compiles
them; Python caches what it imports): this environment sets
PYTHONDONTWRITEBYTECODE, under which flowloop, an editable install here,
would be compiled from source in every process (the figure "compiled
from source" says what that costs) while preprocess_cancellation has pip's
bytecode. So both processes cache theirs
under a PYTHONPYCACHEPREFIX of the test's own, each run once first; the
start-up compiled from source is reported beside, as a figure.
"""

from __future__ import annotations

import logging
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from flowloop.gcode.bulk_planner import Segments, plan_batches
from tests.bench.size import pick
from tests.samples import arc_fitted

PROJECT = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("FLOWLOOP_BENCH_GCODE",
                             PROJECT / "no-bench-gcode")) / "parts.gcode"
EXCERPT = PROJECT / "tests" / "data" / "gcode" / "block_layers_1_2.gcode"
TARGET_BYTES = pick(25_000_000, 300_000)
ROUNDS = pick(5, 1)
# layers of the synthetic arc-fitted file: 5.3 MB, 72,000 arcs (full size)
ARC_LAYERS = pick(6000, 100)


def large_file(folder: Path) -> Path:
    path = folder / "large.gcode"
    if SHARED.is_file():
        whole = SHARED.read_bytes()
        path.write_bytes(whole * max(1, round(TARGET_BYTES / len(whole))))
    else:
        excerpt = EXCERPT.read_bytes()
        body = excerpt.index(b";LAYER_CHANGE")
        layers = b"G92 E0\n" + excerpt[body:]
        path.write_bytes(excerpt[:body]
                         + layers * max(1, TARGET_BYTES // len(layers)))
    return path


def labelled(src: Path, folder: Path) -> Path:
    """src with each layer labelled as one object, in PrusaSlicer's words."""
    path = folder / "labelled.gcode"
    begin = b"; printing object bench_part id:0 copy 0\n"
    end = b"; stop printing object bench_part id:0 copy 0\n"
    head, *layers = src.read_bytes().split(b";LAYER_CHANGE\n")
    path.write_bytes(head + b"".join(b";LAYER_CHANGE\n" + begin + layer + end
                                     for layer in layers))
    return path


def commands(path: Path) -> Tuple[List[str], List[str]]:
    return ([sys.executable, "-m", "flowloop", "annotate", str(path)],
            [sys.executable, "-m", "preprocess_cancellation", str(path)])


def cached(folder: Path) -> Dict[str, str]:
    """The environment of a process whose imports are cached (in folder)."""
    env = dict(os.environ, PYTHONPYCACHEPREFIX=str(folder / "pycache"))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def timed(argv: List[str], src: Path, work: Path,
          env: Optional[Dict[str, str]] = None) -> Tuple[float, float]:
    """(wall s, CPU s) of one whole process rewriting a fresh copy of src."""
    shutil.copyfile(src, work)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run([a if a != "{}" else str(work) for a in argv], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def pairs(src: Path, folder: Path, env: Optional[Dict[str, str]] = None
          ) -> Tuple[Tuple[float, float], Tuple[float, float]]:
    """Medians (wall, CPU) of flowloop and of preprocess_cancellation, run in
    turn so that drift on a shared machine hits both."""
    env = cached(folder) if env is None else env
    work = folder / f"work_{src.name}"
    flowloop_argv, ppc_argv = commands(Path("{}"))
    runs = {"flowloop": [], "ppc": []}
    # warm the page cache and the imports (and their bytecode)
    timed(flowloop_argv, src, work, env)
    timed(ppc_argv, src, work, env)
    for _ in range(ROUNDS):
        runs["flowloop"].append(timed(flowloop_argv, src, work, env))
        runs["ppc"].append(timed(ppc_argv, src, work, env))

    def median(name):
        return tuple(statistics.median(r[k] for r in runs[name]) for k in (0, 1))
    return median("flowloop"), median("ppc")


def test_annotate_whole_process_vs_preprocess_cancellation(tmp_path, bench):
    logging.getLogger("prepropress_cancellation").setLevel(logging.WARNING)
    src = large_file(tmp_path)
    megabytes = src.stat().st_size / 1e6
    (fl_start, _), (ppc_start, _) = pairs(EXCERPT, tmp_path)
    bench.figure("annotate file", megabytes, " MB", goal="")
    bench.ratio("annotate start-up alone (22 kB file), whole process", fl_start,
                ppc_start, " s")
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        (compiling, _), _ = pairs(EXCERPT, tmp_path, dict(os.environ))
        bench.figure("annotate start-up alone, flowloop compiled from source"
                     " (PYTHONDONTWRITEBYTECODE, not counted above)", compiling, " s")
    for case, path in (("no labels", src),
                       ("labelled objects", labelled(src, tmp_path))):
        (fl_wall, fl_cpu), (ppc_wall, ppc_cpu) = pairs(path, tmp_path)
        bench.ratio(f"annotate wall time, whole process with start-up, {case}",
                    fl_wall, ppc_wall, " s", goal="<= 1.0x")
        bench.ratio(f"annotate CPU time, whole process with start-up, {case}",
                    fl_cpu, ppc_cpu, " s")
        bench.ratio(f"annotate wall time without start-up, {case}",
                    fl_wall - fl_start, ppc_wall - ppc_start, " s")

    start = time.perf_counter()
    with open(src, "rb") as f:
        assert sum(len(b) for b in plan_batches(f) if isinstance(b, Segments)) > 0
    planner_s = time.perf_counter() - start
    bench.figure("planner alone, in this process, no labels", planner_s, " s")


def test_annotate_an_arc_fitted_file(tmp_path, bench):
    # No slicer here fits arcs: tests.samples.arc_fitted writes each
    # layer's rings as quarter arcs (G2/G3, relative E) between straight
    # lines, as an arc fitter leaves a file; gcode_arcs makes each one some
    # twelve 1 mm moves, which the planner expands in bulk
    # (preprocess_cancellation refuses a file no slicer's header names, so
    # flowloop's time is a figure of its own: whole process, median)
    path = tmp_path / "arcs.gcode"
    path.write_bytes(arc_fitted(ARC_LAYERS, absolute_e=False))
    env = cached(tmp_path)
    argv, _ = commands(Path("{}"))
    work = tmp_path / "work_arcs.gcode"
    timed(argv, path, work, env)
    wall = statistics.median(timed(argv, path, work, env)[0] for _ in range(ROUNDS))
    megabytes = path.stat().st_size / 1e6
    bench.figure("annotate arc-fitted file (synthetic, relative E)", megabytes,
                 " MB", goal="")
    bench.figure("annotate wall time, whole process with start-up, arc-fitted",
                 wall, " s")
    bench.figure("annotate arc-fitted file, MB per second", megabytes / wall,
                 " MB/s")
