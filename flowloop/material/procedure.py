"""MEASURE_MATERIAL_PROFILE as a procedure: what the printer does next,
decided from what it reports.

The klippy adapter (klippy_extras/measure_profile/) executes and this
module decides. `Procedure` is built from the plan, the bounds, the
[measure_profile] settings, the base profile and the extruder's hardware;
it answers each event with the next action, a small frozen value:

    Say(text)          a line for the console       answer: send()
    Log(text)          a line for the log only      answer: send()
    HeatTo(temp_c)     the heater's own control to temp_c    send()
    HoldPower(pwm)     the heater held at pwm (0..1 of full power)  send()
    Release()          the heater's own control back         send()
    Dwell(seconds)     let print time pass                   send()
    Read()             a temperature reading        answer: send(Reading)
    Extrude(...)       extrude into air             answer: send(Extruded)
    Done(...)          the profile measured: hand it over (the end)
    Stop(reason)       the run ends early, nothing stored (the end)

The flow sensor's grip windows are fed as they close (`window`), a cancel
at any time (`cancel`: the next reading answers Stop). The procedure's
progress is typed state (`progress`); `Status` is [measure_profile]'s whole
status as a value (`as_dict` is what get_status returns).

`PrintMeasurement` decides MEASURE_MATERIAL_PROFILE_PRINT the same way: fed
the windows of a print of the measurement part, it says when the
real-print point is found and which profile that gives.

The order of the procedure is ddPrint's (see flowloop.material.measure):
for each level heat (TEMPS=: to the level; POWERS=: to where the power
holds), hold the power, settle, ramp the flow until grip falls below
MIN_GRIP; then fit the lines. A step whose windows judge nothing runs
again, up to MAX_STEP_RETRIES times.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import (
    Callable,
    Generator,
    List,
    Optional,
    Tuple,
    Union,
)

from ..errors import FlowloopError
from ..window import Window
from . import fit as fl_fit
from . import measure as fl_measure
from .profile import (
    MAX_FLOW_MM3_S,
    MAX_TEMP_C,
    MIN_TEMP_C,
    Bounds,
    MeasuredPoint,
    Profile,
    min_grip_of,
    profile_line,
)

READING_INTERVAL_S = 1.0    # between temperature readings while waiting
MAX_MOVE_S = 1.0            # per extrude-only move of a step
MAX_STEP_RETRIES = 2        # a step without a judged window runs again
# The step's grip window length is the longest of the sensor's last judged
# windows (this many windows back)
RECENT_WINDOWS = 8
NAME = "MEASURE_MATERIAL_PROFILE"
PRINT_NAME = "MEASURE_MATERIAL_PROFILE_PRINT"
SHUT_DOWN = "Klipper shut down"

# The bounds of the commands' numbers, as flowloop.numbers reads them (the
# adapter passes them on; docs/reference.md states them)
TEMP_PARAM = {'minimum': MIN_TEMP_C, 'maximum': MAX_TEMP_C}     # degC
FLOW_PARAM = {'above': 0.0, 'maximum': MAX_FLOW_MM3_S}          # mm^3/s
MIN_GRIP_PARAM = {'above': 0.0, 'below': 1.0}
SWITCH_PARAM = {'minimum': 0, 'maximum': 1}                    # ACTIVATE=
LAYER_PARAM = {'minimum': 1}


# --- the actions -------------------------------------------------------------
@dataclass(frozen=True)
class Say:
    text: str


@dataclass(frozen=True)
class Log:
    text: str


@dataclass(frozen=True)
class HeatTo:
    temp_c: float


@dataclass(frozen=True)
class HoldPower:
    pwm: float          # share of the heater's full power (0..1)


@dataclass(frozen=True)
class Release:
    pass


@dataclass(frozen=True)
class Dwell:
    seconds: float


@dataclass(frozen=True)
class Read:
    pass


@dataclass(frozen=True)
class Extrude:
    flow_mm3_s: float
    speed_mm_s: float               # filament mm/s
    moves_s: Tuple[float, ...]      # one extrude-only move each, in order


@dataclass(frozen=True)
class Done:
    profile: Profile
    fitted: fl_fit.MeasuredLines
    points: Tuple[MeasuredPoint, ...]
    lines: Tuple[str, ...]          # for the console, after the command's name
    notes: Tuple[str, ...] = ()     # said before the lines


@dataclass(frozen=True)
class Stop:
    reason: str
    notes: Tuple[str, ...] = ()     # said before the reason


Action = Union[Say, Log, HeatTo, HoldPower, Release, Dwell, Read, Extrude,
               Done, Stop]


# --- the events --------------------------------------------------------------
@dataclass(frozen=True)
class Reading:
    time_s: float                       # print time
    temp_c: float
    power: float                        # the heater's power, 0..1
    sensor_fault: Optional[str] = None  # the flow sensor's fault, if any
    heater_stop: Optional[str] = None   # why the fixed power was cut, if it was


@dataclass(frozen=True)
class Extruded:
    start_s: float      # print time the step's moves start
    end_s: float        # and end


# --- what the procedure is built from ----------------------------------------
@dataclass(frozen=True)
class Settings:
    """[measure_profile]'s options."""
    step_time_s: float = fl_measure.DEFAULT_STEP_TIME_S
    settle_time_s: float = fl_measure.DEFAULT_SETTLE_TIME_S
    max_settle_time_s: float = fl_measure.DEFAULT_MAX_SETTLE_TIME_S
    section: str = "measure_profile"

    def __post_init__(self):
        if self.max_settle_time_s < self.settle_time_s:
            raise FlowloopError(f"{self.max_settle_time_s:g} is below"
                                f" settle_time {self.settle_time_s:g}")


@dataclass(frozen=True)
class Hardware:
    """What the procedure needs of the extruder, its heater and its sensor."""
    filament_area_mm2: float
    nozzle_diameter_mm: float
    max_power: float          # the heater's (POWERS= are shares of it)
    # The grip window length until the sensor's judged windows show it
    # (flowloop.sensor.grip.DEFAULT_WINDOW_MM)
    window_mm: float

    @property
    def filament_diameter_mm(self) -> float:
        """The filament diameter the area is of (to the micrometre)."""
        return round((4.0 * self.filament_area_mm2 / math.pi) ** 0.5, 3)


def bounds_for(base: Optional[Profile], min_temp_c: Optional[float],
               max_temp_c: Optional[float], heater_max_temp_c: float,
               heater_min_temp_c: float = 0.0) -> Bounds:
    """A measurement's bounds: MIN_TEMP= / MAX_TEMP= where given, else the
    base profile's; within the heater's min_temp..max_temp (the run sets
    its heater to the minimum, and Klipper refuses a target outside them).
    The recommended temperature is the base's (else the middle), within the
    bounds."""
    if base is not None:
        b = base.bounds
        min_temp_c = b.min_temp_c if min_temp_c is None else min_temp_c
        max_temp_c = b.max_temp_c if max_temp_c is None else max_temp_c
    if min_temp_c is None or max_temp_c is None:
        raise FlowloopError(
            "no active profile on this extruder gives the temperature "
            "limits: activate one, or give MIN_TEMP= and MAX_TEMP=")
    max_temp_c = min(max_temp_c, heater_max_temp_c)
    min_temp_c = max(min_temp_c, heater_min_temp_c)
    if not min_temp_c < max_temp_c:
        raise FlowloopError(f"MIN_TEMP: {min_temp_c:g} degC is not below the"
                            f" maximum {max_temp_c:g} degC")
    recommended = ((min_temp_c + max_temp_c) / 2.0 if base is None
                   else base.bounds.recommended_temp_c)
    return Bounds(min_temp_c=min_temp_c, max_temp_c=max_temp_c,
                  recommended_temp_c=min(max(recommended, min_temp_c),
                                         max_temp_c))


def missing_sensor(sensor_name: Optional[str], extruder_name: str) -> str:
    """Why a run cannot start when no flow sensor judges its grip: the one
    [measure_profile] names (`sensor`), else one on the extruder (which one
    that is: flowloop.host.klipper_config.find_flow_sensor)."""
    which = (f"[flow_sensor {sensor_name}]" if sensor_name
             else f"a [flow_sensor] on {extruder_name}")
    return f"EXTRUDER: {which} is needed to judge grip"


def start_refusal(busy: bool, printing: bool = False,
                  paused: bool = False) -> Optional[str]:
    """Why a measurement may not start, or None: one runs already (or a
    print is watched), a print is running, or the printer is paused (the
    real-print measurement asks only the first)."""
    if busy:
        return "a measurement is running already"
    if printing:
        return "a print is running; nothing changed"
    if paused:
        return ("the printer is paused (RESUME or CLEAR_PAUSE first);"
                " nothing changed")
    return None


def check_sensor(sensor_name: str, fault: Optional[str]) -> None:
    """FlowloopError if the sensor is faulted: a watch started then is
    never told (the fault reached its subscribers before the watch)."""
    if fault is not None:
        raise FlowloopError(f"flow sensor {sensor_name} is faulted ({fault})")


def check_active(extruder_name: str, active: bool) -> None:
    """FlowloopError unless the extruder measured is the toolhead's."""
    if not active:
        raise FlowloopError(f"{extruder_name} is not the active extruder"
                            " (activate it first)")


def handed_over(command: str, name: str, extruder_name: str,
                activate: bool) -> str:
    """What is said once Moonraker took a measured profile."""
    return (f"{command}: profile '{name}' handed to Moonraker"
            + (f" and activated on {extruder_name}" if activate else ""))


def not_stored(command: str, name: str, error: str) -> str:
    """What is said when Moonraker did not take it."""
    return (f"{command}: profile '{name}' measured but not stored ({error}):"
            " is Moonraker's [flowloop] component loaded?")


# What a run relies on between two of its turns on the G-code queue:
# (toolhead position, extruder heater's target, the heater's control object)
Held = Tuple[Tuple[float, ...], float, object]


def turn_stop(extruder_name: str, stop_reason: Optional[str], paused: bool,
              left: Optional[Held], now: Optional[Held]) -> Optional[str]:
    """Why a run must end before its next turn, or None: the procedure's
    stop (a cancel, a shutdown: Procedure.stop_reason), PAUSE, or a command
    since the last turn that moved the toolhead, changed the heater's
    target or replaced its control (left: what the last turn left, None
    before the first)."""
    if stop_reason:
        return stop_reason
    if paused:
        return "PAUSE cancels a measurement"
    if left is None or now is None:
        return None
    (position, target, control), (now_position, now_target, now_control) = \
        left, now
    if now_position != position:
        return "the toolhead was moved by another command: cancelled"
    if now_target != target:
        return (f"{extruder_name}'s target was changed by another command"
                f" ({target:g} -> {now_target:g} degC): cancelled")
    if now_control is not control:
        return (f"{extruder_name}'s heater control was replaced by another"
                " command: cancelled")
    return None


# --- the status --------------------------------------------------------------
@dataclass(frozen=True)
class Result:
    """A measured profile's line, as the status shows it."""
    name: str
    slope_mm3_s_per_c: float
    temp_c: float
    flow_mm3_s: float
    note: str

    @classmethod
    def of(cls, profile: Profile, kind: str = "into_air") -> Result:
        line = getattr(profile.lines, kind)
        return cls(profile.name, line.slope_mm3_s_per_c, line.temp_c,
                   line.flow_mm3_s, profile.provenance.note)


@dataclass(frozen=True)
class Progress:
    """How far a run is: its level (from 1), the flow of its step, the
    points of the levels done."""
    levels: int = 0
    level: Optional[int] = None
    flow: Optional[float] = None
    points: Tuple[MeasuredPoint, ...] = ()


class State(str, enum.Enum):
    """What [measure_profile] is doing (the value is what the status says)."""
    IDLE = "idle"
    RUNNING = "running"             # MEASURE_MATERIAL_PROFILE
    WATCHING = "watching"           # MEASURE_MATERIAL_PROFILE_PRINT's print
    MEASURED = "measured"           # not (yet) stored
    STORED = "stored"               # handed to Moonraker
    ABORTED = "aborted"             # ended early: nothing stored


@dataclass(frozen=True)
class Status:
    """[measure_profile]'s status; each change is one of its transitions."""
    state: State = State.IDLE
    name: Optional[str] = None
    level: Optional[int] = None
    flow: Optional[float] = None
    levels: int = 0
    message: str = ""
    points: Tuple[MeasuredPoint, ...] = ()
    result: Optional[Result] = None
    heater_control: Optional[str] = None   # the heater's control's class
    heater_pwm: Optional[float] = None     # while held at a fixed power

    def with_progress(self, progress: Progress) -> Status:
        return dataclasses.replace(
            self, level=progress.level, flow=progress.flow,
            levels=progress.levels, points=progress.points)

    def with_heater(self, control: Optional[str],
                    pwm: Optional[float] = None) -> Status:
        """The heater's control (its class name), at pwm while held."""
        return dataclasses.replace(self, heater_control=control,
                                   heater_pwm=pwm)

    def running(self, name: str) -> Status:
        """A MEASURE_MATERIAL_PROFILE started (its progress follows)."""
        return dataclasses.replace(self, state=State.RUNNING, name=name,
                                   result=None, message="")

    def watching(self, name: str, message: str) -> Status:
        """A MEASURE_MATERIAL_PROFILE_PRINT started: nothing of a run left."""
        return dataclasses.replace(
            self, state=State.WATCHING, name=name, level=None, levels=0,
            flow=None, points=(), result=None, message=message)

    def aborted(self, message: str) -> Status:
        return dataclasses.replace(self, state=State.ABORTED, message=message)

    def measured(self, done: Done, kind: str) -> Status:
        """A profile measured (kind: its line), before the hand-over."""
        return dataclasses.replace(self, state=State.MEASURED,
                                   points=done.points,
                                   result=Result.of(done.profile, kind))

    def stored(self, message: str) -> Status:
        return dataclasses.replace(self, state=State.STORED, message=message)

    def not_stored(self, message: str) -> Status:
        """Moonraker did not take it: still measured, and why."""
        return dataclasses.replace(self, message=message)

    def as_dict(self) -> dict:
        """The status as klippy hands it out: built once per Status (every
        change makes a new one), so a poll returns the same dict."""
        built = self.__dict__.get('_dict')
        if built is None:
            built = self._build_dict()
            object.__setattr__(self, '_dict', built)
        return built

    def _build_dict(self) -> dict:
        return {
            'state': self.state.value, 'name': self.name, 'level': self.level,
            'flow': self.flow, 'levels': self.levels, 'message': self.message,
            'points': [{'temp_c': p.temp_c, 'flow_mm3_s': p.flow_mm3_s,
                        'grip': p.grip, 'heater_pwm': p.heater_pwm}
                       for p in self.points],
            'result': (None if self.result is None
                       else dataclasses.asdict(self.result)),
            'heater_control': self.heater_control,
            'heater_pwm': self.heater_pwm}


# --- the procedure -----------------------------------------------------------
# The fixed-power watchdog: why a level must end now, or None
# (flowloop.control.watchdog.stop_reason with the run's limits; passed in,
# as material sits below control).
Watchdog = Callable[..., Optional[str]]
_Steps = Generator[Action, Optional[Union[Reading, Extruded]], Action]


class Procedure:
    """One MEASURE_MATERIAL_PROFILE: start(), then send() the answer to
    each action until Done or Stop."""

    def __init__(self, name: str, plan: fl_measure.Plan, bounds: Bounds,
                 settings: Settings, base: Optional[Profile],
                 hardware: Hardware, watchdog: Watchdog, source: str = NAME):
        self.name, self.plan, self.bounds = name, plan, bounds
        self.settings, self.base, self.hardware = settings, base, hardware
        self.watchdog, self.source = watchdog, source
        self.progress = Progress(levels=len(plan.levels))
        self.cancel_reason: Optional[str] = None
        self.shut_down = False
        self.windows: List[Window] = []
        self.holds: List[Tuple[float, float]] = []  # (mean power, temp) heated
        self.last: Optional[Action] = None
        self._steps: _Steps = self._run()
        self._waiting: Optional[type] = None   # the answer expected

    # --- events --------------------------------------------------------------
    def start(self) -> Action:
        return self._next(lambda: next(self._steps))

    def send(self, answer: Optional[Union[Reading, Extruded]] = None) -> Action:
        if isinstance(self.last, (Done, Stop)):
            return self.last
        if (self._waiting is None) != (answer is None) or (
                answer is not None and not isinstance(answer, self._waiting)):
            raise TypeError(f"{type(self.last).__name__} is answered with"
                            f" {getattr(self._waiting, '__name__', 'None')},"
                            f" not {answer!r}")
        return self._next(lambda: self._steps.send(answer))

    def window(self, window: Window) -> None:
        """A grip window the run's sensor closed (any time)."""
        self.windows.append(window)

    def cancel(self, reason: str) -> None:
        """Stop at the next reading (the latest reason is the one said)."""
        self.cancel_reason = reason

    def shutdown(self) -> None:
        """Klipper shut down: stop at the next reading (a cancel before it
        is still the reason said)."""
        self.shut_down = True

    @property
    def stop_reason(self) -> Optional[str]:
        """Why the run must stop now (a cancel, a shutdown), or None."""
        return self.cancel_reason or (SHUT_DOWN if self.shut_down else None)

    def _next(self, step: Callable[[], Action]) -> Action:
        try:
            action = step()
        except StopIteration as e:
            action = e.value
        self.last = action
        self._waiting = {Read: Reading, Extrude: Extruded}.get(type(action))
        return action

    # --- the run -------------------------------------------------------------
    def _run(self) -> _Steps:
        try:
            points = yield from self._levels()
            fitted = fl_fit.fit_points("into_air", points, fl_measure.PWM_MAX)
            hardware = self.hardware
            profile = fl_fit.measured_profile(
                self.name, self.base, fitted, points, self.bounds,
                hardware.nozzle_diameter_mm, hardware.filament_diameter_mm,
                self.plan.min_grip, self.source)
        except FlowloopError as e:
            return Stop(str(e))
        return Done(profile, fitted, tuple(points), tuple(fitted.lines()))

    def _levels(self):
        plan = self.plan
        points: List[MeasuredPoint] = []
        for i, level in enumerate(plan.levels):
            where = (f"level {i + 1}/{len(plan.levels)}"
                     f" ({plan.describe_level(level)})")
            self._progress(level=i + 1, flow=None)
            point = yield from self._level(where, level)
            yield Release()
            points.append(point)
            self._progress(points=tuple(points))
            yield Say(f"{where}: limit {point.flow_mm3_s:.2f} mm^3/s at"
                      f" {point.temp_c:.1f} degC, grip {point.grip:.3f}")
        return points

    def _progress(self, **changes):
        self.progress = dataclasses.replace(self.progress, **changes)

    def _level(self, where, level):
        if self.plan.by == "temperature":
            yield Say(f"{where}: heating to {level:g} degC")
            pwm = yield from self._heat_and_settle(level)
        else:
            pwm = level * self.hardware.max_power
            yield from self._heat_to_power(where, pwm)
        yield Say(f"{where}: heater held at {pwm:.1%} power, settling")
        yield HoldPower(pwm)
        readings = yield from self._settle(fixed=True)
        settled_c = readings[-1].temp_c
        return (yield from self._ramp(where, pwm, settled_c))

    def _heat_to_power(self, where, pwm):
        """Heat (the heater's own control) to where pwm holds the nozzle,
        from the powers that held the temperatures so far."""
        bounds = self.bounds
        if not self.holds:
            recommended = bounds.recommended_temp_c
            yield from self._hold_at(recommended, f"{where}: heating to"
                                     f" {recommended:g} degC for the power"
                                     " that holds it")
        for _ in range(fl_measure.POWER_LEVEL_TRIES):
            temp_c = fl_measure.power_level_target(
                pwm, self.holds, bounds.min_temp_c, bounds.max_temp_c)
            if temp_c is None:
                return
            yield from self._hold_at(temp_c, f"{where}: heating to"
                                     f" {temp_c:.1f} degC, where {pwm:.1%}"
                                     " power should hold")

    def _hold_at(self, temp_c, say):
        """Say so, heat to temp_c and note the power that holds it."""
        yield Say(say)
        power = yield from self._heat_and_settle(
            temp_c, fl_measure.POWER_LEVEL_WAITS)
        self.holds.append((power, temp_c))

    def _heat_and_settle(self, temp_c, waits=1):
        """Heat with the heater's own control; the mean power that held
        temp_c, over a settle_time after `waits` more once settled (the
        approach's extra power left out)."""
        yield HeatTo(temp_c)
        for _ in range(waits + 1):
            readings = yield from self._settle(fixed=False, target_c=temp_c)
        return sum(r.power for r in readings) / len(readings)

    def _settle(self, fixed, target_c=None):
        """Readings until the temperature holds still (and, heating, is
        near target_c); at a fixed power each one is watched."""
        settings = self.settings
        readings: List[Reading] = []
        while True:
            reading = yield from self._read(watch=fixed)
            readings.append(reading)
            start = readings[0].time_s
            near = target_c is None or abs(reading.temp_c - target_c) <= \
                fl_measure.SETTLE_BAND_C
            if near and fl_measure.settled(
                    [(r.time_s, r.temp_c) for r in readings],
                    settings.settle_time_s):
                return readings
            if reading.time_s - start > settings.max_settle_time_s:
                raise FlowloopError(
                    f"the temperature did not settle within"
                    f" {settings.max_settle_time_s:g} s (at"
                    f" {reading.temp_c:.1f} degC)")
            yield Dwell(READING_INTERVAL_S)

    def _read(self, watch=True, settled_c=None, previous=None):
        """A reading; FlowloopError when the run must end (a cancel or a
        shutdown, then none is asked for; at a fixed power the heater's
        cut or the watchdog)."""
        if self.stop_reason:
            raise FlowloopError(self.stop_reason)
        reading = yield Read()
        if self.stop_reason:
            raise FlowloopError(self.stop_reason)
        if watch:
            reason = reading.heater_stop or self.watchdog(
                temp_c=reading.temp_c, now_s=reading.time_s,
                settled_c=settled_c, previous=previous,
                sensor_fault=reading.sensor_fault)
            if reason:
                raise FlowloopError(reason)
        return reading

    def _ramp(self, where, pwm, settled_c):
        plan = self.plan
        expected = None
        if self.base is not None:
            expected = profile_line(self.base, 1.0).flow_mm3_s(settled_c)
        start = plan.ramp_start(expected)
        # One reading before the first step; after that, the one after a
        # step is the one before the next
        reading = yield from self._read(True, settled_c)
        for flow in plan.flows(start):
            self._progress(flow=flow)
            previous = (reading.time_s, reading.temp_c)
            step = yield from self._step(flow, plan.step_windows(flow, expected))
            yield Say(f"{where}: {step.describe()}")
            reading = yield from self._read(True, settled_c, previous)
            if step.grip < plan.min_grip:
                if flow == start and not plan.start_given:
                    yield Say(f"{where}: the first step slipped already; the"
                              " point is what the hotend melted (a lower"
                              " START_FLOW= confirms it)")
                return fl_measure.limit_point(step, pwm, reading.temp_c)
        raise FlowloopError(
            f"{where}: grip stayed above {plan.min_grip:g} up to MAX_FLOW"
            f" {plan.max_flow_mm3_s:g} mm^3/s (raise MAX_FLOW)")

    def _step(self, flow, windows):
        """Extrude into air at flow for step_time (at least `windows` grip
        windows); the step judged."""
        area = self.hardware.filament_area_mm2
        # The sensor's window length, as its judged windows show it
        window_mm = max([float(w.commanded_mm)
                         for w in self.windows[-RECENT_WINDOWS:]
                         if w.grip is not None]
                        or [self.hardware.window_mm])
        duration = fl_measure.step_duration_s(
            self.settings.step_time_s, flow, area, window_mm, windows)
        extrude = Extrude(flow, flow / area, move_times(duration))
        for _ in range(MAX_STEP_RETRIES + 1):
            first = len(self.windows)
            done = yield extrude
            seen = self.windows[first:]
            step = fl_measure.judge_step(seen, done.start_s, done.end_s, flow)
            if step is not None:
                return dataclasses.replace(step, duration_s=duration)
            yield Log(f"no judged window in {done.start_s:.3f}.."
                      f"{done.end_s:.3f}: {seen}")
            # a sensor fault judges nothing: say that instead
            yield from self._read()
        raise FlowloopError(
            f"no grip window was judged at {flow:g} mm^3/s (a longer"
            f" step_time in [{self.settings.section}]?)")


def move_times(duration_s: float, max_move_s: float = MAX_MOVE_S
               ) -> Tuple[float, ...]:
    """A step's extrusion as moves of at most max_move_s, in order (the
    console gets a turn between two)."""
    moves = []
    left = duration_s
    while left > 1e-9:
        moves.append(min(max_move_s, left))
        left -= moves[-1]
    return tuple(moves)


# --- the real-print measurement ----------------------------------------------
def print_base(base: Optional[Profile]) -> Profile:
    """The base profile a real-print measurement needs (the extruder's
    active one), or FlowloopError."""
    if base is None:
        raise FlowloopError(
            "activate the material's profile first: its into-air line"
            " gives the real-print line's slope")
    return base


class PrintMeasurement:
    """One MEASURE_MATERIAL_PROFILE_PRINT: the grip windows of a print of
    the measurement part (flowloop measure-part) until the median grip
    falls below MIN_GRIP (flowloop.material.measure.PrintWatch); its point
    and the base's into-air slope give the real-print line."""

    def __init__(self, name: str, base: Profile, min_grip: Optional[float],
                 hardware: Hardware, source: str = PRINT_NAME):
        self.name, self.base, self.hardware = name, base, hardware
        self.source = source
        self.watch = fl_measure.PrintWatch(min_grip_of(base, min_grip))
        self.layers: List[Tuple[float, float]] = []  # (start, planned flow)

    def add_layer(self, start_s: float, flow_mm3_s: float) -> None:
        """MEASURE_MATERIAL_PROFILE_LAYER: a layer's moves start at start_s."""
        self.layers.append((start_s, flow_mm3_s))

    def window(self, window: Window
               ) -> Optional[Union[Stop, fl_measure.StepResult]]:
        """None: watch on; Stop: a sensor fault ends it; a StepResult: the
        point is found (`finish` it)."""
        if window.faulted:
            return Stop("flow sensor fault: nothing stored")
        return self.watch.add(window)

    def finish(self, step: fl_measure.StepResult) -> Union[Done, Stop]:
        notes: Tuple[str, ...] = ()
        melted = fl_measure.melted_flow(self.watch.recent, self.layers)
        if melted is not None:
            step = dataclasses.replace(step, measured_mm3_s=melted)
        else:
            notes = ("no MEASURE_MATERIAL_PROFILE_LAYER in the file: the flow"
                     " is the windows' own, low by their travel and corners"
                     " (print a part from flowloop measure-part)",)
        point = fl_measure.limit_point(step, None, 0., kind='real_print')
        base = self.base
        try:
            fitted = fl_fit.one_point_lines(
                'real_print', point, base.lines.into_air.slope_mm3_s_per_c)
            profile = fl_fit.measured_profile(
                self.name, base, fitted, [point], base.bounds,
                self.hardware.nozzle_diameter_mm,
                self.hardware.filament_diameter_mm, self.watch.min_grip,
                self.source)
        except FlowloopError as e:
            return Stop(f"{e}; nothing stored", notes)
        line = (f"grip {step.grip:.3f} at {point.flow_mm3_s:.2f} mm^3/s,"
                f" {point.temp_c:.1f} degC: " + fitted.lines()[0])
        return Done(profile, fitted, (point,), (line,), notes)

