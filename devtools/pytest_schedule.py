"""How `make test` spreads the tests over pytest-xdist workers.

Most of the suite waits on something other than the CPU (a Moonraker or
klippy starting, a klippy paced to the clock, a browser), so it runs on more
workers than the machine has cores. Two rules keep that honest:

- A group (one test module on one host, chosen in tests/conftest.py) runs
  whole on one worker, so a stack a module starts once serves all of its
  tests there, as in a serial run.
- A group named ``alone:...`` (tests that measure time or run paced to the
  wall clock) runs on one worker, one test at a time, from the start; every
  other test runs beside it at SCHED_IDLE, so it never takes CPU a paced
  test wants (AloneBesideScheduling). Without an idle class the alone groups
  wait until every other test has finished and then run with nothing beside
  them (AloneLastScheduling).

The groups travel from the workers (which collect) to the scheduler (which
does not) in a file named after xdist's test run id, not as the ``@group``
suffix of ``--dist loadgroup``: pytest 9.2 builds node ids in a way xdist
3.8's suffix no longer reaches, and a suffix would show in every report.
"""

from __future__ import annotations

import json
import os
import resource
import tempfile
import uuid
from pathlib import Path
from typing import Callable, Dict, Optional

import pytest

try:
    from xdist.scheduler.loadscope import LoadScopeScheduling
except ImportError:  # without pytest-xdist pytest runs serially: no scheduler
    LoadScopeScheduling = object

ALONE = "alone:"
# a group that runs when no other test runs at all, not even at SCHED_IDLE
# (the firmware-in-the-loop tier: its simulated MCU lost the clock beside
# idle-class tests, "Timer too close", where the paced klippy tests did not)
QUIET = "quiet:"
# at most this many quiet groups run at once, side by side
QUIET_RUNNERS = 2
# cores per simulated printer: two side by side on two cores lost the clock
# once in three runs of `make test` on a machine where a printer (its
# simulator, klippy and test) took 0.45 of a core ("Timer too close" in
# test_fil_closed_loop: a klippy or its simulator starved for longer than
# klippy schedules ahead); one on two never has
CORES_PER_QUIET_RUNNER = 2
# ... unless the last run's record says a printer takes at most this much of
# a core (its tests' CPU seconds over their wall seconds): two then take at
# most half of one of the two, where the machine above gave them 0.9 (on a
# machine at 0.19, two side by side passed four runs of the quiet phase
# alone and two beside a busy process)
QUIET_LOAD_FOR_TWO = 0.25
# Without a record, the quiet groups that ran whole in this run decide it:
# at once where they took at most QUIET_LOAD_FOR_TWO, one at a time only
# once they ran this long (a module's share varies: 0.14-0.33 of a core on
# a machine where the phase took 0.20, the first printer's start the most)
QUIET_MEASURE_S = 60.0


def is_alone(scope: str) -> bool:
    return scope.startswith(ALONE)


def is_quiet(scope: str) -> bool:
    return scope.startswith(QUIET)


def runs_apart(scope: str) -> bool:
    return is_alone(scope) or is_quiet(scope)


def _groups_path(testrunuid: str) -> Path:
    return Path(tempfile.gettempdir()) / f"flowloop-xdist-groups-{testrunuid}.json"


DURATIONS_KEY = "flowloop/test-durations"
# CPU seconds (the test's process and every child it reaped) per test, kept
# beside the wall times: what the README's "Where the time goes" reads.
CPU_KEY = "flowloop/test-cpu"


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class CpuMeter:
    """In whichever process runs the tests (a worker or a serial run): the
    CPU used since the last report, attached to each report as the user
    property ``cpu`` (a daemon a module fixture starts is counted when the
    fixture's teardown reaps it)."""

    def __init__(self) -> None:
        self.last = _cpu_seconds()

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_makereport(self, item, call):
        outcome = yield
        now = _cpu_seconds()
        outcome.get_result().user_properties.append(("cpu", now - self.last))
        self.last = now


def order(config, items, group_of: Callable[[object], Optional[str]],
          fallback: Callable[[object], int]) -> None:
    """Sort items in place for the workers: the groups that took longest in
    the last run first (so that no long group starts last), alone groups
    last; tests never timed (a fresh clone) by fallback(item) after the
    timed ones. Within a group, tests keep their order."""
    cache = getattr(config, "cache", None)
    took = cache.get(DURATIONS_KEY, {}) if cache is not None else {}
    total: Dict[str, float] = {}
    for item in items:
        key = group_of(item) or item.nodeid
        total[key] = total.get(key, 0.0) + took.get(item.nodeid, 0.0)

    def rank(item):
        key = group_of(item) or item.nodeid
        return (runs_apart(key), is_quiet(key), -total[key], fallback(item))
    items.sort(key=rank)


class DurationRecorder:
    """In the controller (or a serial run): each test's setup, call and
    teardown time, kept in pytest's cache for order() in the next run."""

    def __init__(self) -> None:
        self.took: Dict[str, float] = {}
        self.cpu: Dict[str, float] = {}

    def pytest_runtest_logreport(self, report) -> None:
        self.took[report.nodeid] = self.took.get(report.nodeid, 0.0) + report.duration
        for name, value in report.user_properties:
            if name == "cpu":
                self.cpu[report.nodeid] = self.cpu.get(report.nodeid, 0.0) + value

    def pytest_sessionfinish(self, session) -> None:
        cache = getattr(session.config, "cache", None)
        if cache is None or not self.took:
            return
        cache.set(DURATIONS_KEY, {**cache.get(DURATIONS_KEY, {}), **self.took})
        if self.cpu:
            cache.set(CPU_KEY, {**cache.get(CPU_KEY, {}), **self.cpu})


def configure(config) -> None:
    """In the controller, before the workers start: fix the run id both
    sides name the groups file after, and time the tests for order()."""
    config.pluginmanager.register(CpuMeter(), "flowloop-cpu")
    if getattr(config, "workerinput", None) is not None:
        return
    if config.getoption("testrunuid", default=None) is None:
        config.option.testrunuid = uuid.uuid4().hex
    config.pluginmanager.register(DurationRecorder(), "flowloop-durations")


def publish(config, items, group_of: Callable[[object], Optional[str]]) -> None:
    """In a worker, after collection: write {node id: group} for the
    scheduler (every worker collects the same items and writes the same)."""
    workerinput = getattr(config, "workerinput", None)
    if workerinput is None:
        return
    groups = {item.nodeid: group for item in items
              if (group := group_of(item)) is not None}
    path = _groups_path(workerinput["testrunuid"])
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name)
    with os.fdopen(fd, "w") as out:
        json.dump(groups, out)
    os.replace(tmp, path)


class AloneLastScheduling(LoadScopeScheduling):
    """xdist's loadscope over the published groups, with the ``alone:``
    groups last and on one worker alone.

    The test's conftest sorts the alone groups to the end of the collection,
    so they are the last units of the work queue. Once they are all that is
    left, the first worker to ask for more becomes their runner and every
    other worker is told to finish what it holds and stop. (An xdist worker
    keeps its last test until it gets more work or is told to stop: it needs
    the next test to know which fixtures to tear down; so idle workers
    cannot just wait.) The runner gets the alone groups when no other worker
    has a test left, and runs them after its own, one test at a time.
    """

    def __init__(self, config, log=None) -> None:
        super().__init__(config, log)
        # the collection's order is the plan (longest first, alone last):
        # not xdist's reordering by the number of tests in a group
        config.option.loadscopereorder = False
        self.runner = None
        self._groups: Optional[Dict[str, str]] = None

    def _split_scope(self, nodeid: str) -> str:
        if self._groups is None:   # asked once collection is complete
            path = _groups_path(self.config.getoption("testrunuid"))
            self._groups = json.loads(path.read_text()) if path.exists() else {}
            path.unlink(missing_ok=True)
        return self._groups.get(nodeid, nodeid)

    def _alone_next(self) -> bool:
        return bool(self.workqueue) and runs_apart(next(iter(self.workqueue)))

    def _others_done(self) -> bool:
        return not any(self._pending_of(work)
                       for node, work in self.assigned_work.items()
                       if node is not self.runner)

    def _reschedule(self, node) -> None:
        if node.shutting_down or not self._alone_next():
            super()._reschedule(node)
            return
        if self.runner is None:
            self.runner = node
        elif node is not self.runner:
            node.shutdown()
        self._hand_alone_to_runner()

    def _assign_work_unit(self, node) -> None:
        # xdist's first distribution assigns directly: guard it here too
        if self._alone_next():
            if self.runner is None:
                self.runner = node
            if node is not self.runner or not self._others_done():
                return
        super()._assign_work_unit(node)

    def _hand_alone_to_runner(self) -> None:
        if self.runner is None or not self._alone_next() or not self._others_done():
            return
        if self.runner not in self.assigned_work:   # the runner went away
            self.runner = None
            return
        while self.workqueue:
            self._assign_work_unit(self.runner)

    def mark_test_complete(self, node, item_index: int, duration: float = 0) -> None:
        super().mark_test_complete(node, item_index, duration)
        # a stopping worker's last test does not reschedule it: look here
        self._hand_alone_to_runner()

    def remove_node(self, node):
        crashed = super().remove_node(node)
        if node is self.runner:
            self.runner = None
            for other in self.nodes:
                self._reschedule(other)
        return crashed


class AloneBesideScheduling(AloneLastScheduling):
    """xdist's loadscope over the published groups, the ``alone:`` groups
    on one worker (the runner) from the start, one test at a time, while
    the other workers run the rest beside it at SCHED_IDLE (see
    Priority): Linux gives an idle-class process only the CPU no normal
    one wants, and places a waking normal process on a CPU that runs only
    idle-class ones as if it were free. So a paced test keeps the clock it
    would have alone, and the machine's second core is not left idle for
    the minutes the paced tests take (they wait on the clock, not the CPU).

    The runner takes the next alone group whenever it asks for work, and
    the rest once none is left; the others never get an alone group.

    The ``quiet:`` groups come last, once every other test has finished,
    on up to quiet_runners() workers side by side (each runs one simulated
    printer: one per two cores, or two where the last run's record says a
    printer takes little of a core; without a record, where that would
    decide, two are kept and the first quiet group runs alone until this
    run's own figures of it decide: _quiet_width), and never beside any
    other test. A
    worker keeps the last test it was given until it gets more (see
    AloneLastScheduling), so a worker that joins
    the quiet phase still holds one test of the earlier phase: it is given
    its first quiet group (the shortest left) only while every other quiet
    worker waits too, one such worker at a time, and that held test runs
    alone. Where idle classes are not to be had, AloneLastScheduling's
    order holds for alone and quiet groups alike.
    """

    def __init__(self, config, log=None) -> None:
        super().__init__(config, log)
        self.beside = None   # the worker the alone groups run on
        self.quiet_runners: list = []   # the workers kept for the quiet phase
        self.quiet_phase = False        # only quiet groups were left
        self._wanted: Optional[int] = None
        # the quiet phase's width waits for its first group's load in this
        # run (measures_in_run): one printer runs until then
        self._measuring = False

    def _runners_wanted(self) -> int:
        """quiet_runners() at the quiet phase's load in the last run
        (decided once: the groups are known by the quiet phase); without
        one where the load decides (measures_in_run), QUIET_RUNNERS are
        kept while this run measures it (_quiet_width)."""
        if self._wanted is None:
            quiet = [i for i, g in (self._groups or {}).items() if is_quiet(g)]
            load = quiet_load(getattr(self.config, "cache", None), quiet)
            self._measuring = measures_in_run(load)
            self._wanted = QUIET_RUNNERS if self._measuring else quiet_runners(load)
        return self._wanted

    def _quiet_width(self) -> int:
        """How many quiet groups may run at once now: while measuring, one,
        until a quiet group has run whole in this run; then quiet_runners()
        at its load (its tests' CPU over their wall time, as the record
        keeps them: DurationRecorder's figures of this run)."""
        wanted = self._runners_wanted()
        if not self._measuring:
            return wanted
        done = [i for work in self.assigned_work.values()
                for scope, unit in work.items()
                if is_quiet(scope) and all(unit.values()) for i in unit]
        recorder = self.config.pluginmanager.get_plugin("flowloop-durations")
        if not done or recorder is None:
            return 1
        load = quiet_load(_Record(recorder), done)
        if load is None or (load > QUIET_LOAD_FOR_TWO
                            and sum(recorder.took.get(i, 0.0) for i in done)
                            < QUIET_MEASURE_S):
            return 1
        self._measuring = False
        self._wanted = quiet_runners(load)
        return self._wanted

    def _alone_next(self) -> bool:   # the quiet phase: only quiet groups left
        return bool(self.workqueue) and all(is_quiet(s) for s in self.workqueue)

    # -- the quiet phase
    def _pending(self, node) -> int:
        return self._pending_of(self.assigned_work.get(node, {}))

    def _holds_earlier_test(self, node) -> bool:
        """Whether node still has a test of the earlier phase to run."""
        return any(not done for scope, unit in self.assigned_work.get(node, {}).items()
                   if not is_quiet(scope) for done in unit.values())

    def _running(self, node) -> bool:
        """Whether node runs a test now (or will without being given more:
        a worker told to stop runs every test it holds)."""
        pending = self._pending(node)
        return pending > 1 or (pending > 0 and node.shutting_down)

    def _keep_for_quiet(self, node) -> bool:
        if node in self.quiet_runners:
            return True
        if node.shutting_down or len(self.quiet_runners) >= self._runners_wanted():
            return False
        self.quiet_runners.append(node)
        return True

    def _join_quiet(self, node) -> None:
        self.quiet_phase = True
        if not self._keep_for_quiet(node) and not node.shutting_down:
            node.shutdown()
        self._feed_quiet()

    def _give(self, node, shortest: bool = False) -> None:
        if shortest:   # the queue is longest first
            self.workqueue.move_to_end(next(reversed(self.workqueue)), last=False)
        LoadScopeScheduling._assign_work_unit(self, node)

    def _feed_quiet(self) -> None:
        runners = [n for n in self.quiet_runners
                   if n in self.assigned_work and not n.shutting_down]
        if not self.quiet_phase or not runners:
            return
        others = [n for n in self.assigned_work if n not in runners]
        if any(self._pending(n) for n in others):
            return                    # they finish what they hold first
        width = self._quiet_width()
        held = [n for n in runners if self._holds_earlier_test(n)]
        busy = [n for n in runners if n not in held]   # in the quiet phase
        if held:
            # an earlier phase's test runs alone: once every runner waits
            if any(self._running(n) for n in runners):
                return
            if not self.workqueue:
                held[0].shutdown()    # it runs that test, and stops
                return
            if len(busy) < width:
                self._give(held[0], shortest=True)   # it runs, then quiet ones
                return
            if not self._measuring:
                held[0].shutdown()    # not wanted: it runs that test, and stops
                return
            # measuring: the one in the quiet phase goes on alone
        running = sum(self._running(n) for n in busy)
        for node in busy:
            if self._running(node):
                continue
            if not self.workqueue:
                node.shutdown()
            elif running < width:
                self._give(node)
                running += 1
            elif not self._measuring:
                node.shutdown()       # not wanted: it stops

    def _next_scope(self, node) -> Optional[str]:
        if self.beside is None or self.beside not in self.assigned_work:
            self.beside = node
        alone = node is self.beside
        fallback = None
        for scope in self.workqueue:
            if is_quiet(scope):
                continue
            if is_alone(scope) == alone:
                return scope
            if fallback is None and not is_alone(scope):
                fallback = scope
        return fallback   # the alone groups' worker, out of them: the rest

    def _assign_work_unit(self, node) -> None:
        if self._alone_next():
            self._join_quiet(node)
            return
        scope = self._next_scope(node)
        if scope is None:
            return
        self.workqueue.move_to_end(scope, last=False)
        LoadScopeScheduling._assign_work_unit(self, node)

    def _reschedule(self, node) -> None:
        if self.quiet_phase or (self._alone_next() and not node.shutting_down):
            self._join_quiet(node)
            return
        if node.shutting_down or not self.workqueue:
            super()._reschedule(node)
            return
        if self._next_scope(node) is None:
            # nothing left this worker may run: what remains are the alone
            # groups (another worker's) and the quiet ones. It waits for
            # the quiet phase holding its last test, or finishes what it
            # holds (it keeps its last test until told) and stops
            if not (any(is_quiet(s) for s in self.workqueue)
                    and self._keep_for_quiet(node)):
                node.shutdown()
            return
        LoadScopeScheduling._reschedule(self, node)

    def _hand_alone_to_runner(self) -> None:
        self._feed_quiet()

    def remove_node(self, node):
        crashed = LoadScopeScheduling.remove_node(self, node)
        if node in self.quiet_runners:
            self.quiet_runners.remove(node)
        if self.quiet_phase and not self.quiet_runners:
            for other in self.nodes:   # the quiet workers went away
                self._join_quiet(other)
        self._feed_quiet()
        return crashed


def quiet_runners(load: Optional[float] = None) -> int:
    """Workers of the quiet phase: one simulated printer per
    CORES_PER_QUIET_RUNNER cores, at most QUIET_RUNNERS, or two on two or
    three cores where the quiet phase's load in the last run (quiet_load,
    cores per printer) was at most QUIET_LOAD_FOR_TWO; FLOWLOOP_QUIET_RUNNERS
    sets the number (1 runs them one at a time)."""
    wanted = os.environ.get("FLOWLOOP_QUIET_RUNNERS")
    if wanted is not None:
        return max(1, int(wanted))
    cores = os.cpu_count() or 1
    runners = max(1, min(QUIET_RUNNERS, cores // CORES_PER_QUIET_RUNNER))
    if runners < 2 <= cores and load is not None and load <= QUIET_LOAD_FOR_TWO:
        runners = 2
    return runners


def measures_in_run(load: Optional[float]) -> bool:
    """Whether the quiet phase's width waits for this run's own measure of
    the load: where the load decides it (two or three cores) and the last
    run's record has none (a fresh clone), unless FLOWLOOP_QUIET_RUNNERS
    sets it."""
    if load is not None or os.environ.get("FLOWLOOP_QUIET_RUNNERS") is not None:
        return False
    return quiet_runners(None) < 2 <= (os.cpu_count() or 1)


class _Record:
    """DurationRecorder's figures of this run, read as quiet_load reads the
    record (pytest's cache)."""

    def __init__(self, recorder: DurationRecorder) -> None:
        self.values = {DURATIONS_KEY: recorder.took, CPU_KEY: recorder.cpu}

    def get(self, key, default):
        return self.values.get(key, default)


def quiet_load(cache, quiet_ids) -> Optional[float]:
    """The cores a quiet group's printer took in the last run: its tests'
    CPU seconds (each test's process and every child it reaped: the
    printer's simulator and klippy at the module's teardown) over their
    wall seconds, over every quiet test; None unless the record has them
    all (a fresh clone, or tests new since)."""
    if cache is None or not quiet_ids:
        return None
    took = cache.get(DURATIONS_KEY, {})
    cpu = cache.get(CPU_KEY, {})
    if any(i not in took or i not in cpu for i in quiet_ids):
        return None
    wall = sum(took[i] for i in quiet_ids)
    return sum(cpu[i] for i in quiet_ids) / wall if wall > 0 else None


def idle_class_available() -> bool:
    return hasattr(os, "SCHED_IDLE") and hasattr(os, "sched_setscheduler")


def scheduler_class():
    return AloneBesideScheduling if idle_class_available() else AloneLastScheduling


class Priority:
    """In each worker of a parallel run: an alone test runs at the normal
    policy, every other test (and what it starts: children inherit the
    policy) at SCHED_IDLE, so that nothing beside a paced test takes CPU
    from it (AloneBesideScheduling)."""

    def __init__(self, is_alone_item: Callable[[object], bool]) -> None:
        self.is_alone_item = is_alone_item

    @pytest.hookimpl(tryfirst=True)
    def pytest_runtest_setup(self, item) -> None:
        policy = os.SCHED_OTHER if self.is_alone_item(item) else os.SCHED_IDLE
        if os.sched_getscheduler(0) != policy:
            try:
                os.sched_setscheduler(0, policy, os.sched_param(0))
            except OSError:   # leaving the idle class needs the right to
                pass


def prioritise(config, is_alone_item: Callable[[object], bool]) -> None:
    """In a worker of a run with more than one: register Priority."""
    workerinput = getattr(config, "workerinput", None)
    if (workerinput is not None and workerinput.get("workercount", 1) > 1
            and idle_class_available()):
        config.pluginmanager.register(Priority(is_alone_item), "flowloop-priority")

