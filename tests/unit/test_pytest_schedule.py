"""`make test`'s scheduler (devtools/pytest_schedule.py), run by pytest-xdist
on a small suite whose tests write down when they ran: the alone groups run
with no other test beside them, the rest in parallel, and nothing hangs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Optional

import pytest

from devtools import pytest_schedule

pytest.importorskip("xdist")

PROJECT = Path(__file__).resolve().parents[2]

CONFTEST = """
import json, os, time
import pytest
from devtools import pytest_schedule

SCHEDULER = getattr(pytest_schedule, os.environ["SCHEDULER"])
if os.environ.get("CORES"):   # the machine the scheduler believes it runs on
    os.cpu_count = lambda: int(os.environ["CORES"])
if os.environ.get("QUIET_MEASURE_S"):   # how long its own figures must run
    pytest_schedule.QUIET_MEASURE_S = float(os.environ["QUIET_MEASURE_S"])
if os.environ.get("QUIET_LOAD_FOR_TWO"):   # the load two may run side by side at
    pytest_schedule.QUIET_LOAD_FOR_TWO = float(os.environ["QUIET_LOAD_FOR_TWO"])

@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    return SCHEDULER(config, log)

def pytest_configure(config):
    pytest_schedule.configure(config)
    if SCHEDULER is pytest_schedule.AloneBesideScheduling:
        pytest_schedule.prioritise(
            config, lambda item: item.name.startswith("test_alone"))

def pytest_collection_modifyitems(config, items):
    def group(item):
        mark = item.get_closest_marker("group")
        return mark.args[0] if mark else None
    pytest_schedule.publish(config, items, group)

@pytest.fixture(autouse=True)
def record(request):
    start = time.monotonic()
    yield
    with open(os.environ["RUNS"], "a") as out:
        out.write(json.dumps([request.node.name, start, time.monotonic(),
                              os.environ.get("PYTEST_XDIST_WORKER"),
                              os.sched_getscheduler(0)]) + "\\n")
"""

SUITE = """
import time
import pytest

@pytest.mark.parametrize("n", range({normal})){group}
def test_normal(n):
    time.sleep(0.3)

@pytest.mark.parametrize("n", range({alone}))
@pytest.mark.group("alone:paced")
def test_alone(n):
    time.sleep(0.3)

@pytest.mark.parametrize("n", range({alone}))
@pytest.mark.group("alone:other")
def test_alone_too(n):
    time.sleep(0.3)

@pytest.mark.parametrize("n", range({quiet}))
@pytest.mark.group("quiet:fil")
def test_quiet(n):
    time.sleep(0.3)

@pytest.mark.parametrize("n", range({quiet}))
@pytest.mark.group("quiet:fil_other")
def test_quiet_too(n):
    time.sleep(0.3)
"""


# what the inner runs see: no plugin or setting of this run's environment,
# only where it keeps bytecode (devtools.stack.cache_bytecode)
BARE_ENV = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(PROJECT)}
if sys.pycache_prefix:
    BARE_ENV["PYTHONPYCACHEPREFIX"] = sys.pycache_prefix


LAST, BESIDE = "AloneLastScheduling", "AloneBesideScheduling"
# A bound that catches a hung run, not a slow one: under `make test` these
# runs are idle-class (SCHED_IDLE, as every test that is not alone) and get
# only the CPU nothing else wants; beside a busy process at normal priority
# one took over 120 s (it takes 5 s alone)
HUNG_S = 900
# the inner suites use no Hypothesis: its plugin's import cost each of
# their processes 0.4 s of CPU
NO_HYPOTHESIS = "no:hypothesispytest"


def run_suite(tmp_path, normal: int, alone: int, workers: int, per_test_group=False,
              scheduler=LAST, quiet: int = 0, quiet_runners: Optional[int] = 2,
              suite: str = SUITE, env: Optional[dict] = None):
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers = group\n")
    (tmp_path / "conftest.py").write_text(CONFTEST)
    # ungrouped, each test its own unit (the klippy .test files), or one group
    group = "" if per_test_group else '\n@pytest.mark.group("module")'
    suite = suite.format(normal=normal, alone=alone, group=group, quiet=quiet)
    (tmp_path / "test_suite.py").write_text(textwrap.dedent(suite))
    runs = tmp_path / "runs.jsonl"
    runners = {} if quiet_runners is None else {
        "FLOWLOOP_QUIET_RUNNERS": str(quiet_runners)}
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         "-p", NO_HYPOTHESIS, "-n", str(workers), "test_suite.py"],
        cwd=tmp_path, capture_output=True, text=True, timeout=HUNG_S,
        env={**BARE_ENV, "RUNS": str(runs), "SCHEDULER": scheduler,
             **runners, **(env or {})})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return [json.loads(line) for line in runs.read_text().splitlines()]


def overlaps(a, b) -> bool:
    return a[1] < b[2] and b[1] < a[2]


@pytest.mark.parametrize("per_test_group", [False, True])
def test_alone_groups_run_after_the_rest_with_nothing_beside_them(
        tmp_path, per_test_group):
    runs = run_suite(tmp_path, normal=9, alone=2, workers=3,
                     per_test_group=per_test_group)
    alone = [r for r in runs if r[0].startswith("test_alone")]
    normal = [r for r in runs if r[0].startswith("test_normal")]
    assert len(alone) == 4 and len(normal) == 9
    for a in alone:
        assert not [r[0] for r in runs if r is not a and overlaps(a, r)], a
    if per_test_group:
        # the rest did run side by side
        assert any(overlaps(a, b) for a in normal for b in normal if a is not b)
    assert min(a[1] for a in alone) >= max(n[2] for n in normal)


IDLE_CLASS = pytest.mark.skipif(not pytest_schedule.idle_class_available(),
                                reason="no SCHED_IDLE on this system")


@IDLE_CLASS
@pytest.mark.parametrize("per_test_group", [True, False])
def test_alone_groups_run_on_one_worker_with_the_rest_beside_them_idle(
        tmp_path, per_test_group):
    runs = run_suite(tmp_path, normal=9, alone=2, workers=3,
                     per_test_group=per_test_group, scheduler=BESIDE, quiet=2)
    alone = [r for r in runs if r[0].startswith("test_alone")]
    normal = [r for r in runs if r[0].startswith("test_normal")]
    quiet = [r for r in runs if r[0].startswith("test_quiet")]
    assert len(alone) == 4 and len(normal) == 9 and len(quiet) == 4
    # the quiet groups: last, two side by side (one worker each), and
    # beside no other test, not even an idle one (a worker's last test of
    # the earlier phase, held until it is given more, runs with nothing
    # beside it)
    for q in quiet:
        assert not [r[0] for r in runs
                    if not r[0].startswith("test_quiet") and overlaps(q, r)], q
    assert any(overlaps(a, b) for a in quiet for b in quiet if a[0] != b[0])
    for group in ("test_quiet[", "test_quiet_too["):
        assert len({q[3] for q in quiet if q[0].startswith(group)}) == 1
    # most of the rest ran before them (all but held tests)
    first_quiet = min(q[1] for q in quiet)
    assert sum(r[2] > first_quiet for r in alone + normal) <= 2
    # one runner, one alone test at a time, at the normal policy
    assert len({a[3] for a in alone}) == 1
    assert not any(overlaps(a, b) for a in alone for b in alone if a is not b)
    assert {a[4] for a in alone} == {os.SCHED_OTHER}
    # the rest ran beside them (not after), every one at the idle policy
    beside = [n for n in normal if any(overlaps(n, a) for a in alone)]
    assert beside, runs
    assert {n[4] for n in normal} == {os.SCHED_IDLE}
    # the runner started with the alone groups
    first = min(r for r in runs if r[3] == alone[0][3])
    assert first[0].startswith("test_alone")


@pytest.mark.parametrize("scheduler", [LAST, BESIDE])
def test_a_run_of_alone_tests_only_runs_them_one_at_a_time(tmp_path, scheduler):
    runs = run_suite(tmp_path, normal=0, alone=3, workers=3, scheduler=scheduler)
    assert len(runs) == 6
    assert not any(overlaps(a, b) for a in runs for b in runs if a is not b)


@IDLE_CLASS
@pytest.mark.parametrize("quiet_runners", [1, 2])
def test_quiet_groups_alone_run_side_by_side_up_to_the_quiet_runners(
        tmp_path, quiet_runners):
    runs = run_suite(tmp_path, normal=0, alone=0, workers=3, scheduler=BESIDE,
                     quiet=3, quiet_runners=quiet_runners)
    assert len(runs) == 6
    side_by_side = any(overlaps(a, b) for a in runs for b in runs if a is not b)
    assert side_by_side == (quiet_runners == 2)


MEASURED = """
import os, time
import pytest

def work():
    # a simulated printer's test: waiting (little CPU), or busy
    if os.environ.get("QUIET_BUSY"):
        start = time.process_time()
        while time.process_time() - start < 0.3:
            pass
    else:
        time.sleep(0.3)

@pytest.mark.parametrize("n", range(2))
@pytest.mark.group("module")
def test_normal(n):
    time.sleep(0.3)
""" + "".join(f"""
@pytest.mark.parametrize("n", range(2))
@pytest.mark.group("quiet:{name}")
def test_quiet_{name}(n):
    work()
""" for name in "abcd")


@IDLE_CLASS
@pytest.mark.parametrize("busy", [False, True])
def test_a_fresh_clone_measures_the_quiet_load_before_two_run_side_by_side(
        tmp_path, busy):
    # two cores, no record (a fresh clone), no FLOWLOOP_QUIET_RUNNERS: the
    # first quiet group runs with nothing beside it; then two side by side
    # where its tests took little CPU (waiting), one at a time where they
    # kept a core busy (decided once they ran QUIET_MEASURE_S: here 0.5 s,
    # the first group's two tests; the second worker is then stopped).
    # Two may share at a third of QUIET_LOAD_FOR_TWO here: a test that keeps
    # a core busy counts the CPU it got over its wall time, which was 0.35
    # beside a `make test` (this test runs in the idle class) and under a
    # quarter beside `make test` and a busy process, where it then ran side
    # by side (2026-11-30); a waiting one takes 0.03 (its own overhead)
    env = {"CORES": "2", "QUIET_MEASURE_S": "0.5",
           "QUIET_LOAD_FOR_TWO": f"{pytest_schedule.QUIET_LOAD_FOR_TWO / 3:g}",
           **({"QUIET_BUSY": "1"} if busy else {})}
    runs = run_suite(tmp_path, normal=0, alone=0, workers=3, scheduler=BESIDE,
                     quiet_runners=None, suite=MEASURED, env=env)
    assert len(runs) == 10
    quiet = sorted((r for r in runs if r[0].startswith("test_quiet")),
                   key=lambda r: r[1])
    first = [r for r in quiet if r[0].split("[")[0] == quiet[0][0].split("[")[0]]
    assert not any(overlaps(a, b) for a in first for b in runs if b not in first)
    side_by_side = any(overlaps(a, b) for a in quiet for b in quiet
                       if a[0].split("[")[0] != b[0].split("[")[0])
    assert side_by_side == (not busy)


@pytest.mark.parametrize("cores, load, runners, measures", [
    (1, None, 1, False), (2, None, 1, True), (3, None, 1, True),
    (4, None, 2, False), (16, None, 2, False),
    # two on two cores only where a printer took little of a core; without
    # a record, there, the run measures it (AloneBesideScheduling)
    (1, 0.1, 1, False), (2, 0.19, 2, False), (3, 0.25, 2, False),
    (2, 0.26, 1, False), (2, 0.45, 1, False), (4, 0.45, 2, False)])
def test_one_simulated_printer_per_two_cores_or_two_that_take_little(
        monkeypatch, cores, load, runners, measures):
    monkeypatch.delenv("FLOWLOOP_QUIET_RUNNERS", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: cores)
    assert pytest_schedule.quiet_runners(load) == runners
    assert pytest_schedule.measures_in_run(load) == measures
    monkeypatch.setenv("FLOWLOOP_QUIET_RUNNERS", "3")
    assert pytest_schedule.quiet_runners(load) == 3
    assert not pytest_schedule.measures_in_run(load)


class Cache:
    """pytest's cache as the scheduler reads it."""

    def __init__(self, values):
        self.values = values

    def get(self, key, default):
        return self.values.get(key, default)


RECORD = Cache({pytest_schedule.DURATIONS_KEY: {"q1": 10.0, "q2": 30.0, "n": 5.0},
                pytest_schedule.CPU_KEY: {"q1": 2.0, "q2": 6.0, "n": 5.0}})


def test_the_quiet_load_is_the_quiet_tests_cpu_over_their_wall_time():
    assert pytest_schedule.quiet_load(RECORD, ["q1", "q2"]) == pytest.approx(0.2)
    assert pytest_schedule.quiet_load(RECORD, ["n"]) == pytest.approx(1.0)
    # a quiet test the record lacks (new since, or a fresh clone): unknown
    assert pytest_schedule.quiet_load(RECORD, ["q1", "new"]) is None
    assert pytest_schedule.quiet_load(Cache({}), ["q1"]) is None
    assert pytest_schedule.quiet_load(None, ["q1"]) is None
    assert pytest_schedule.quiet_load(RECORD, []) is None


@pytest.mark.parametrize("groups, runners, measuring", [
    ({"q1": "quiet:m1", "q2": "quiet:m2", "n": "m3"}, 2, False),   # load 0.2
    ({"q1": "quiet:m1", "n": "quiet:m3"}, 1, False),               # load 0.47
    # not recorded: two kept while the run measures the load
    ({"q1": "quiet:m1", "new": "quiet:m2"}, 2, True)])
def test_the_scheduler_reads_the_quiet_groups_load_from_the_record(
        monkeypatch, groups, runners, measuring):
    monkeypatch.delenv("FLOWLOOP_QUIET_RUNNERS", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    sched = pytest_schedule.AloneBesideScheduling.__new__(
        pytest_schedule.AloneBesideScheduling)
    sched.config = type("Config", (), {"cache": RECORD})()
    sched._groups, sched._wanted = groups, None
    assert sched._runners_wanted() == runners
    assert sched._measuring == measuring


@pytest.mark.parametrize("scheduler", [LAST, BESIDE])
def test_without_alone_tests_the_run_ends(tmp_path, scheduler):
    assert len(run_suite(tmp_path, normal=5, alone=0, workers=2,
                         per_test_group=True, scheduler=scheduler)) == 5


ORDERED = """
import time

def test_quick():
    pass

def test_slow():
    time.sleep(0.4)

def test_also_quick():
    pass
"""


def test_the_next_run_starts_with_what_took_longest_in_the_last(tmp_path):
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    (tmp_path / "conftest.py").write_text(textwrap.dedent("""
        from devtools import pytest_schedule

        def pytest_configure(config):
            pytest_schedule.configure(config)

        def pytest_collection_modifyitems(config, items):
            pytest_schedule.order(config, items, lambda item: None,
                                  lambda item: 0)
    """))
    (tmp_path / "test_order.py").write_text(ORDERED)

    def collected():
        proc = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", NO_HYPOTHESIS,
             "--collect-only", "test_order.py"],
            cwd=tmp_path, capture_output=True, text=True, timeout=HUNG_S,
            env=BARE_ENV)
        return [line.split("::")[1] for line in proc.stdout.splitlines()
                if "::" in line]
    # never timed: the file's order
    assert collected() == ["test_quick", "test_slow", "test_also_quick"]
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", NO_HYPOTHESIS,
                    "test_order.py"],
                   cwd=tmp_path, check=True, capture_output=True, timeout=HUNG_S,
                   env=BARE_ENV)
    assert collected()[0] == "test_slow"


def test_a_python_the_run_starts_keeps_bytecode_in_the_cache_not_beside_sources(
        tmp_path):
    """devtools.stack.cache_bytecode (called by tests/conftest.py): with
    PYTHONDONTWRITEBYTECODE set, a Python the run starts still keeps its
    bytecode, under the cache's pycache prefix and never in the source's
    folder (a user's Klipper checkout stays as it was)."""
    source = tmp_path / "src"
    source.mkdir()
    (source / "mod.py").write_text("X = 1\n")
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(PROJECT),
           "PYTHONDONTWRITEBYTECODE": "1", "FLOWLOOP_CACHE": str(tmp_path / "cache")}
    script = ("import os, subprocess, sys\n"
              "from devtools import stack\n"
              "stack.cache_bytecode()\n"
              "subprocess.run([sys.executable, '-c', 'import mod'],"
              f" cwd={str(source)!r}, check=True,"
              f" env={{**os.environ, 'PYTHONPATH': {str(source)!r}}})\n")
    subprocess.run([sys.executable, "-c", script], check=True, env=env,
                   timeout=HUNG_S)
    assert not (source / "__pycache__").exists()
    assert list((tmp_path / "cache" / "pycache").rglob("mod.*.pyc"))
