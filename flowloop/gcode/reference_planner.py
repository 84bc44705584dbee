"""The reference flow planner: G-code in, the plastic flow it demands over
print time out, one line at a time in plain Python.

This is the reference: checked against Klipper's own toolhead code
(tests/unit/test_planner_klipper.py) and readable line for line beside it.
What flowloop runs on a file (`flowloop annotate`, the bake, Moonraker's
processor) is flowloop.gcode.bulk_planner, which must give the same events
bit for bit (tests/unit/test_planner_fast.py) and uses this module through
its public surface only: the types of the timeline (`PrinterLimits`,
`Segment`, `Barrier`, `Event`), `Move`, `Planner` with its two seams
(`queue_move`, `flush_queue`) and `HANDLED_COMMANDS`.

The timeline is the one Klipper executes (klippy/toolhead.py, 2026-08):
moves are trapezoids limited by max_velocity and max_accel (max_z_* on Z),
corners by square_corner_velocity (junction deviation) and the extruder's
instantaneous_corner_velocity, and the lookahead is Klipper's own, with its
lazy flush and minimum_cruise_ratio, so a move gets the speeds klippy gives
it. gcode_move's state (G90/G91, M82/M83, G92, M220/M221), arcs split as
gcode_arcs splits them, firmware retraction (G10/G11, SET_RETRACTION) and
SET_VELOCITY_LIMIT/M204 change the moves as they do in klippy; comments are
ignored, and so are commands that do not move the toolhead.

Flow is the plastic that leaves the nozzle: filament pushed back after a
retraction refills the nozzle and is no flow, so an unretract is not a flow
peak. A move that both refills and extrudes spreads its net extrusion over
the move.

`plan_file()` is a generator that holds only Klipper's lookahead queue (about
a second of moves): memory does not grow with the file. Waits whose length
the file does not give (M109, M190, M191, TEMPERATURE_WAIT, G28, PAUSE,
M600) add no print time; each comes out as a `Barrier`, so that a consumer
knows the time across it is not the time the printer will take.
"""

from __future__ import annotations

import codecs
import io
import math
import re
from dataclasses import dataclass, fields
from typing import BinaryIO, Dict, Iterator, List, NamedTuple, Optional, Tuple, Union

from ..errors import FlowloopError

# klippy/toolhead.py
LOOKAHEAD_FLUSH_TIME = 0.150
BUFFER_TIME_HIGH = 1.0
BUFFER_TIME_START = 0.250
# klippy/extras/gcode_move.py: the speed before any F (mm/s).
DEFAULT_SPEED_MM_S = 25.0
# A coordinate, E value or feed rate beyond this is a broken file, not a print.
MAX_ABS_VALUE = 1e9
# Commands after which the printer waits for something the file does not time.
BARRIER_COMMANDS = frozenset(("G28", "M109", "M190", "M191", "TEMPERATURE_WAIT",
                              "PAUSE", "M600", "M0", "M1"))
# klippy/gcode.py: how Klipper splits a traditional command into words.
_ARGS_R = re.compile(r"([A-Z_]+|[A-Z*])")
_FAST_MOVES = (b"G1 ", b"G0 ")
# A move whose numbers Python's float() reads exactly as Klipper splits them
# (Klipper reads "X1E3" as X1 E3, float() as 1000: such lines go the slow way).
_SIMPLE_MOVE = re.compile(rb"G[01](?:[ \t]+[XYZEF][-+]?[0-9.]+)*\s*")


@dataclass(frozen=True)
class PrinterLimits:
    """What Klipper's config says about motion, by its option names.

    None means Klipper's own default, derived as klippy derives it.
    """
    max_velocity: float = 300.0
    max_accel: float = 3000.0
    minimum_cruise_ratio: float = 0.5
    square_corner_velocity: float = 5.0
    max_z_velocity: Optional[float] = None            # max_velocity
    max_z_accel: Optional[float] = None               # max_accel
    nozzle_diameter: float = 0.4
    filament_diameter: float = 1.75
    max_extrude_cross_section: Optional[float] = None  # 4 * nozzle_diameter^2
    max_extrude_only_velocity: Optional[float] = None
    max_extrude_only_accel: Optional[float] = None
    max_extrude_only_distance: float = 50.0
    instantaneous_corner_velocity: float = 1.0
    retract_length: float = 0.0
    retract_speed: float = 20.0
    unretract_extra_length: float = 0.0
    unretract_speed: float = 10.0
    arc_resolution: float = 1.0                        # [gcode_arcs] resolution

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise FlowloopError(f"{f.name} must be a finite number, not {value!r}")
            if f.name in _MAY_BE_ZERO:
                if value < 0.0:
                    raise FlowloopError(f"{f.name} must be >= 0, not {value}")
            elif value <= 0.0:
                raise FlowloopError(f"{f.name} must be above 0, not {value}")
        if self.minimum_cruise_ratio >= 1.0:
            raise FlowloopError("minimum_cruise_ratio must be below 1, not "
                                f"{self.minimum_cruise_ratio}")

    @property
    def filament_area_mm2(self) -> float:
        return math.pi * (self.filament_diameter * 0.5) ** 2

    def derived(self, name: str) -> float:
        """A value Klipper derives when the option is not set (extruder.py)."""
        value = getattr(self, name)
        if value is not None:
            return value
        default_cross_section = 4.0 * self.nozzle_diameter ** 2
        default_ratio = default_cross_section / self.filament_area_mm2
        return {
            "max_z_velocity": self.max_velocity,
            "max_z_accel": self.max_accel,
            "max_extrude_cross_section": default_cross_section,
            "max_extrude_only_velocity": self.max_velocity * default_ratio,
            "max_extrude_only_accel": self.max_accel * default_ratio,
        }[name]


_MAY_BE_ZERO = frozenset(("minimum_cruise_ratio", "square_corner_velocity",
                          "max_extrude_only_distance", "instantaneous_corner_velocity",
                          "retract_length", "unretract_extra_length"))
# PrinterLimits field -> (section, option) of printer.cfg.
CONFIG_OPTIONS = {
    "max_velocity": ("printer", "max_velocity"),
    "max_accel": ("printer", "max_accel"),
    "minimum_cruise_ratio": ("printer", "minimum_cruise_ratio"),
    "square_corner_velocity": ("printer", "square_corner_velocity"),
    "max_z_velocity": ("printer", "max_z_velocity"),
    "max_z_accel": ("printer", "max_z_accel"),
    "nozzle_diameter": ("extruder", "nozzle_diameter"),
    "filament_diameter": ("extruder", "filament_diameter"),
    "max_extrude_cross_section": ("extruder", "max_extrude_cross_section"),
    "max_extrude_only_velocity": ("extruder", "max_extrude_only_velocity"),
    "max_extrude_only_accel": ("extruder", "max_extrude_only_accel"),
    "max_extrude_only_distance": ("extruder", "max_extrude_only_distance"),
    "instantaneous_corner_velocity": ("extruder", "instantaneous_corner_velocity"),
    "retract_length": ("firmware_retraction", "retract_length"),
    "retract_speed": ("firmware_retraction", "retract_speed"),
    "unretract_extra_length": ("firmware_retraction", "unretract_extra_length"),
    "unretract_speed": ("firmware_retraction", "unretract_speed"),
    "arc_resolution": ("gcode_arcs", "resolution"),
}


def limits_from_config(config) -> PrinterLimits:
    """The limits klippy reads from a printer.cfg (a host.klipper_config
    KlipperConfig); options it does not set keep Klipper's defaults."""
    values = {}
    for name, (section, option) in CONFIG_OPTIONS.items():
        if config.has_option(section, option):
            values[name] = config.getfloat(section, option)
    try:
        return PrinterLimits(**values)
    except FlowloopError as e:
        name = str(e).split(" ", 1)[0]
        section, option = CONFIG_OPTIONS.get(name, ("printer", name))
        raise FlowloopError(f"Option '{option}' in section '{section}': "
                            f"{str(e).split(' ', 1)[1]}") from None


class Segment(NamedTuple):
    """One move as Klipper runs it: a trapezoid of speed, and of flow.

    Flow rises linearly from start_flow_mm3_s to flow_mm3_s over accel_s,
    holds, and falls to end_flow_mm3_s over decel_s.
    """
    start_s: float            # print time the move starts
    duration_s: float
    flow_mm3_s: float         # peak (cruise) flow of plastic leaving the nozzle
    accel_s: float
    decel_s: float
    start_flow_mm3_s: float
    end_flow_mm3_s: float
    speed_mm_s: float         # cruise speed of the toolhead (E-only: of E)
    distance_mm: float        # toolhead path (E-only: filament moved)
    filament_mm: float        # net filament extruded (refills excluded)
    offset: int               # byte offset of the G-code line it comes from

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def peak_flow_between(self, t0: float, t1: float) -> float:
        """Highest flow of this move within print times [t0, t1]."""
        a = max(t0, self.start_s) - self.start_s
        b = min(t1, self.start_s + self.duration_s) - self.start_s
        if b < a:
            return 0.0
        cruise_end = self.duration_s - self.decel_s
        if a <= cruise_end and b >= self.accel_s:
            return self.flow_mm3_s
        if b < self.accel_s:   # rising all the way to b
            return self.start_flow_mm3_s + (
                self.flow_mm3_s - self.start_flow_mm3_s) * b / self.accel_s
        # falling from a on
        return self.flow_mm3_s - (self.flow_mm3_s - self.end_flow_mm3_s) * (
            (a - cruise_end) / self.decel_s)


class Barrier(NamedTuple):
    """A wait of unknown length (heating, homing, a pause) at print time time_s."""
    time_s: float
    offset: int               # byte offset just after the barrier's line
    command: str


Event = Union[Segment, Barrier]


class Move:
    """klippy/toolhead.py Move, with what the flow needs (the bulk planner
    reads its fields into arrays)."""
    __slots__ = (
        "start_pos", "end_pos", "axes_d", "axes_r", "move_d", "is_kinematic_move",
        "accel", "junction_deviation", "min_move_t", "max_start_v2",
        "max_cruise_v2", "delta_v2", "next_junction_v2", "max_mcr_start_v2",
        "mcr_delta_v2", "start_v", "cruise_v", "end_v", "accel_t", "cruise_t",
        "decel_t", "flow_per_mm", "filament_mm", "offset")

    def limit_speed(self, speed: float, accel: float) -> None:
        speed2 = speed * speed
        if speed2 < self.max_cruise_v2:
            self.max_cruise_v2 = speed2
            self.min_move_t = self.move_d / speed
        self.accel = min(self.accel, accel)
        self.delta_v2 = 2.0 * self.move_d * self.accel
        self.mcr_delta_v2 = min(self.mcr_delta_v2, self.delta_v2)

    def calc_junction(self, prev_move: Move, instant_corner_v: float) -> None:
        if not self.is_kinematic_move or not prev_move.is_kinematic_move:
            return
        # The extruder as Klipper's extra axis (kinematics/extruder.py).
        diff_r = self.axes_r[3] - prev_move.axes_r[3]
        # min() of Klipper's candidates, written out (this runs for every move)
        max_start_v2 = self.max_cruise_v2
        if diff_r:
            ea_v2 = (instant_corner_v / diff_r) ** 2
            if ea_v2 < max_start_v2:
                max_start_v2 = ea_v2
        if prev_move.max_cruise_v2 < max_start_v2:
            max_start_v2 = prev_move.max_cruise_v2
        if prev_move.next_junction_v2 < max_start_v2:
            max_start_v2 = prev_move.next_junction_v2
        reach_v2 = prev_move.max_start_v2 + prev_move.delta_v2
        if reach_v2 < max_start_v2:
            max_start_v2 = reach_v2
        axes_r = self.axes_r
        prev_axes_r = prev_move.axes_r
        junction_cos_theta = -(axes_r[0] * prev_axes_r[0]
                               + axes_r[1] * prev_axes_r[1]
                               + axes_r[2] * prev_axes_r[2])
        sin_theta_d2 = math.sqrt(max(0.5 * (1.0 - junction_cos_theta), 0.0))
        cos_theta_d2 = math.sqrt(max(0.5 * (1.0 + junction_cos_theta), 0.0))
        one_minus_sin_theta_d2 = 1.0 - sin_theta_d2
        if one_minus_sin_theta_d2 > 0.0 and cos_theta_d2 > 0.0:
            r_jd = sin_theta_d2 / one_minus_sin_theta_d2
            move_jd_v2 = r_jd * self.junction_deviation * self.accel
            pmove_jd_v2 = r_jd * prev_move.junction_deviation * prev_move.accel
            quarter_tan_theta_d2 = 0.25 * sin_theta_d2 / cos_theta_d2
            move_centripetal_v2 = self.delta_v2 * quarter_tan_theta_d2
            pmove_centripetal_v2 = prev_move.delta_v2 * quarter_tan_theta_d2
            for v2 in (move_jd_v2, pmove_jd_v2, move_centripetal_v2,
                       pmove_centripetal_v2):
                if v2 < max_start_v2:
                    max_start_v2 = v2
        self.max_start_v2 = max_start_v2
        mcr_v2 = prev_move.max_mcr_start_v2 + prev_move.mcr_delta_v2
        self.max_mcr_start_v2 = mcr_v2 if mcr_v2 < max_start_v2 else max_start_v2

    def set_junction(self, start_v2: float, cruise_v2: float, end_v2: float) -> None:
        half_inv_accel = 0.5 / self.accel
        accel_d = (cruise_v2 - start_v2) * half_inv_accel
        decel_d = (cruise_v2 - end_v2) * half_inv_accel
        cruise_d = self.move_d - accel_d - decel_d
        self.start_v = start_v = math.sqrt(start_v2)
        self.cruise_v = cruise_v = math.sqrt(cruise_v2)
        self.end_v = end_v = math.sqrt(end_v2)
        self.accel_t = accel_d / ((start_v + cruise_v) * 0.5)
        self.cruise_t = cruise_d / cruise_v
        self.decel_t = decel_d / ((end_v + cruise_v) * 0.5)


class _LookAhead:
    """klippy/toolhead.py LookAheadQueue, line for line."""

    def __init__(self) -> None:
        self.queue: List[Move] = []
        self.junction_flush = BUFFER_TIME_HIGH

    def flush(self, lazy: bool = False) -> List[Move]:
        self.junction_flush = LOOKAHEAD_FLUSH_TIME
        update_flush_count = lazy
        queue = self.queue
        flush_count = len(queue)
        junction_info: list = [None] * flush_count
        next_start_v2 = next_mcr_start_v2 = peak_cruise_v2 = 0.0
        pending_cv2_assign = 0
        for i in range(flush_count - 1, -1, -1):
            move = queue[i]
            reachable_start_v2 = next_start_v2 + move.delta_v2
            start_v2 = move.max_start_v2
            if reachable_start_v2 < start_v2:
                start_v2 = reachable_start_v2
            cruise_v2 = None
            pending_cv2_assign += 1
            reach_mcr_start_v2 = next_mcr_start_v2 + move.mcr_delta_v2
            mcr_start_v2 = move.max_mcr_start_v2
            if reach_mcr_start_v2 < mcr_start_v2:
                mcr_start_v2 = reach_mcr_start_v2
            if mcr_start_v2 < reach_mcr_start_v2:
                if (mcr_start_v2 + move.mcr_delta_v2 > next_mcr_start_v2
                        or pending_cv2_assign > 1):
                    if update_flush_count and peak_cruise_v2:
                        flush_count = i + pending_cv2_assign
                        update_flush_count = False
                    peak_cruise_v2 = (mcr_start_v2 + reach_mcr_start_v2) * 0.5
                cruise_v2 = min((start_v2 + reachable_start_v2) * 0.5,
                                move.max_cruise_v2, peak_cruise_v2)
                pending_cv2_assign = 0
            junction_info[i] = (move, start_v2, cruise_v2, next_start_v2)
            next_start_v2 = start_v2
            next_mcr_start_v2 = mcr_start_v2
        if update_flush_count or not flush_count:
            return []
        prev_cruise_v2 = 0.0
        for i in range(flush_count):
            move, start_v2, cruise_v2, next_start_v2 = junction_info[i]
            if cruise_v2 is None:
                cruise_v2 = min(prev_cruise_v2, start_v2)
            move.set_junction(min(start_v2, cruise_v2), cruise_v2,
                              min(next_start_v2, cruise_v2))
            prev_cruise_v2 = cruise_v2
        res = queue[:flush_count]
        del queue[:flush_count]
        return res

    def add_move(self, move: Move, instant_corner_v: float) -> bool:
        self.queue.append(move)
        if len(self.queue) == 1:
            return False
        move.calc_junction(self.queue[-2], instant_corner_v)
        self.junction_flush -= move.min_move_t
        return self.junction_flush <= 0.0


class Planner:
    """Klipper's gcode_move, toolhead and lookahead, fed one line at a time.

    `line()` returns the events that line completes (most lines: none);
    `finish()` flushes what is left at the end of the file.
    """

    def __init__(self, limits: PrinterLimits = PrinterLimits()):
        self.limits = limits
        self.area = limits.filament_area_mm2
        # toolhead
        self.max_velocity = limits.max_velocity
        self.max_accel = limits.max_accel
        self.min_cruise_ratio = limits.minimum_cruise_ratio
        self.square_corner_velocity = limits.square_corner_velocity
        self._calc_junction_deviation()
        self.max_z_velocity = limits.derived("max_z_velocity")
        self.max_z_accel = limits.derived("max_z_accel")
        self.max_e_velocity = limits.derived("max_extrude_only_velocity")
        self.max_e_accel = limits.derived("max_extrude_only_accel")
        self.max_e_dist = limits.max_extrude_only_distance
        self.max_extrude_ratio = (limits.derived("max_extrude_cross_section")
                                  / self.area)
        self.instant_corner_v = limits.instantaneous_corner_velocity
        self.lookahead = _LookAhead()
        self.commanded_pos = [0.0, 0.0, 0.0, 0.0]
        self.print_time = 0.0
        # gcode_move
        self.last_position = [0.0, 0.0, 0.0, 0.0]
        self.base_position = [0.0, 0.0, 0.0, 0.0]
        self.absolute_coord = self.absolute_extrude = True
        self.speed = DEFAULT_SPEED_MM_S
        self.speed_factor = 1.0 / 60.0
        self.extrude_factor = 1.0
        # firmware_retraction
        self.retract_length = limits.retract_length
        self.retract_speed = limits.retract_speed
        self.unretract_extra_length = limits.unretract_extra_length
        self.unretract_speed = limits.unretract_speed
        self.is_retracted = False
        # gcode_arcs: plane as (alpha, beta, helical) axis indexes
        self.arc_axes = (0, 1, 2)
        # filament pulled back and not yet pushed in again (mm)
        self.retracted_mm = 0.0
        self._out: List[Event] = []
        self._number = 0
        self._text = ""             # the line being planned (slow path)
        self._raw = b""             # the line being planned, as read

    # --- reading lines ------------------------------------------------------------

    def line(self, raw: bytes, offset: int, number: int) -> List[Event]:
        """Plan one line of G-code (bytes, with or without its newline)."""
        if number == 1 and raw.startswith(codecs.BOM_UTF8):
            # a UTF-8 byte-order mark (Windows editors write one) is no command
            raw, offset = raw[len(codecs.BOM_UTF8):], offset + len(codecs.BOM_UTF8)
        if b"\0" in raw:
            raise FlowloopError(f"line {number}: binary data, not G-code text")
        end = offset + len(raw)
        cpos = raw.find(b";")
        if cpos >= 0:
            raw = raw[:cpos]
        if raw[:3] in _FAST_MOVES and _SIMPLE_MOVE.fullmatch(raw) \
                and self._fast_g1(raw, offset, number):
            pass
        else:
            raw = raw.strip()
            if not raw:
                return []
            self._slow_line(raw, offset, number, end)
        if self._out:
            out, self._out = self._out, []
            return out
        return []

    def _fast_g1(self, raw: bytes, offset: int, number: int) -> bool:
        """'G1 X.. Y.. E.. F..' as slicers write it; False: not that simple."""
        x = y = z = e = f = None
        try:
            for word in raw.split()[1:]:
                key = word[0]
                if key == 88:            # X
                    x = float(word[1:])
                elif key == 89:          # Y
                    y = float(word[1:])
                elif key == 69:          # E
                    e = float(word[1:])
                elif key == 70:          # F
                    f = float(word[1:])
                elif key == 90:          # Z
                    z = float(word[1:])
        except ValueError:
            return False
        for v in (x, y, z, e, f):
            if v is not None and not -MAX_ABS_VALUE <= v <= MAX_ABS_VALUE:
                return False
        self._number, self._offset, self._raw = number, offset, raw
        last, base = self.last_position, self.base_position
        if self.absolute_coord:
            if x is not None:
                last[0] = x + base[0]
            if y is not None:
                last[1] = y + base[1]
            if z is not None:
                last[2] = z + base[2]
        else:
            if x is not None:
                last[0] += x
            if y is not None:
                last[1] += y
            if z is not None:
                last[2] += z
        if e is not None:
            e *= self.extrude_factor
            if self.absolute_coord and self.absolute_extrude:
                last[3] = e + base[3]
            else:
                last[3] += e
        if f is not None:
            if f <= 0.0:
                raise self._error("invalid speed")
            self.speed = f * self.speed_factor
        self._move(last, self.speed)
        return True

    def _slow_line(self, raw: bytes, offset: int, number: int, end: int) -> None:
        try:
            text = raw.decode("ascii").upper()
        except UnicodeDecodeError:
            raise FlowloopError(f"line {number}: not G-code text "
                                f"({raw[:40]!r})") from None
        self._number, self._text, self._raw = number, text, raw
        self._offset = offset
        cmd, args = self._klipper_split(text)
        handler = self._handlers.get(cmd)
        if handler is not None:
            handler(self, args)
        if cmd in BARRIER_COMMANDS:
            self.flush_queue()
            self._out.append(Barrier(self.print_time, end, cmd))

    def finish(self) -> List[Event]:
        self.flush_queue()
        out, self._out = self._out, []
        return out

    def _error(self, msg: str) -> FlowloopError:
        text = self._raw.strip().decode("ascii", "replace")
        return FlowloopError(f"line {self._number}: {msg}: '{text}'")

    @staticmethod
    def _klipper_split(text: str):
        """Command and parameters as klippy/gcode.py splits a line."""
        parts = _ARGS_R.split(text)
        if "".join(parts[:2]) == "N":
            cmd = "".join(parts[3:5]).strip()
        else:
            cmd = "".join(parts[:3]).strip()
        return cmd, {parts[i]: parts[i + 1].strip() for i in range(1, len(parts), 2)}

    def _number_value(self, key: str, text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise self._error(f"unable to parse {key}") from None
        if not math.isfinite(value) or abs(value) > MAX_ABS_VALUE:
            raise self._error(f"absurd value {key}{text}")
        return value

    def _floats(self, args: Dict[str, str], keys: str) -> Dict[str, float]:
        return {k: self._number_value(k, args[k]) for k in keys if k in args}

    def _extended(self) -> Dict[str, float]:
        """KEY=value parameters of an extended command (numbers only)."""
        params = {}
        for word in self._text.split()[1:]:
            key, sep, value = word.partition("=")
            if sep:
                params[key] = self._number_value(f"{key}=", value)
        return params

    # --- gcode_move -----------------------------------------------------------------

    def _g1(self, params: Dict[str, float]) -> None:
        last, base = self.last_position, self.base_position
        for axis, pos in (("X", 0), ("Y", 1), ("Z", 2), ("E", 3)):
            if axis in params:
                v = params[axis]
                absolute_coord = self.absolute_coord
                if pos == 3:
                    v *= self.extrude_factor
                    if not self.absolute_extrude:
                        absolute_coord = False
                if absolute_coord:
                    last[pos] = v + base[pos]
                else:
                    last[pos] += v
        if "F" in params:
            gcode_speed = params["F"]
            if gcode_speed <= 0.0:
                raise self._error("invalid speed")
            self.speed = gcode_speed * self.speed_factor
        self._move(last, self.speed)

    def _g92(self, args) -> None:
        params = self._floats(args, "XYZE")
        offsets = [params.get(a) for a in "XYZE"]
        for i, offset in enumerate(offsets):
            if offset is not None:
                if i == 3:
                    offset *= self.extrude_factor
                self.base_position[i] = self.last_position[i] - offset
        if offsets == [None, None, None, None]:
            self.base_position[:4] = self.last_position[:4]

    def _m220(self, args) -> None:
        s = self._floats(args, "S").get("S", 100.0)
        if s <= 0.0:
            raise self._error("S must be above 0")
        value = s / (60.0 * 100.0)
        self.speed = self.speed / self.speed_factor * value
        self.speed_factor = value

    def _m221(self, args) -> None:
        s = self._floats(args, "S").get("S", 100.0)
        if s <= 0.0:
            raise self._error("S must be above 0")
        new_extrude_factor = s / 100.0
        last_e_pos = self.last_position[3]
        e_value = (last_e_pos - self.base_position[3]) / self.extrude_factor
        self.base_position[3] = last_e_pos - e_value * new_extrude_factor
        self.extrude_factor = new_extrude_factor

    def _g20(self, args) -> None:
        raise self._error("inches (G20) are not supported, as in Klipper")

    def _g28(self, args) -> None:
        # Homed axes end at their endstops; the file does not say where: 0.
        self.flush_queue()
        axes = [i for i, a in enumerate("XYZ") if a in args]
        for i in axes or (0, 1, 2):
            self.commanded_pos[i] = self.last_position[i] = 0.0

    # --- toolhead -------------------------------------------------------------------

    def _calc_junction_deviation(self) -> None:
        scv2 = self.square_corner_velocity ** 2
        self.junction_deviation = scv2 * (math.sqrt(2.0) - 1.0) / self.max_accel
        self.mcr_pseudo_accel = self.max_accel * (1.0 - self.min_cruise_ratio)

    def _set_velocity_limit(self, args) -> None:
        params = self._extended()
        checks = (("VELOCITY", "max_velocity", 0.0, None),
                  ("ACCEL", "max_accel", 0.0, None),
                  ("SQUARE_CORNER_VELOCITY", "square_corner_velocity", None, 0.0),
                  ("MINIMUM_CRUISE_RATIO", "min_cruise_ratio", None, 0.0))
        for key, attr, above, minval in checks:
            if key not in params:
                continue
            value = params[key]
            if (above is not None and value <= above) or (
                    minval is not None and value < minval) or (
                    key == "MINIMUM_CRUISE_RATIO" and value >= 1.0):
                raise self._error(f"{key} out of range")
            setattr(self, attr, value)
        self._calc_junction_deviation()

    def _m204(self, args) -> None:
        params = self._floats(args, "SPT")
        accel = params.get("S")
        if accel is None:
            if "P" not in params or "T" not in params:
                return          # Klipper only answers "Invalid M204 command"
            accel = min(params["P"], params["T"])
        if accel <= 0.0:
            raise self._error("acceleration must be above 0")
        self.max_accel = accel
        self._calc_junction_deviation()

    def _g4(self, args) -> None:
        delay = self._floats(args, "P").get("P", 0.0)
        if delay < 0.0:
            raise self._error("P must be >= 0")
        self.flush_queue()
        self.print_time += delay / 1000.0

    def _m400(self, args) -> None:
        # The queue drains, and the next move starts BUFFER_TIME_START later.
        self.flush_queue()
        self.print_time += BUFFER_TIME_START

    def _move(self, newpos: List[float], speed: float) -> None:
        start = self.commanded_pos
        dx = newpos[0] - start[0]
        dy = newpos[1] - start[1]
        dz = newpos[2] - start[2]
        de = newpos[3] - start[3]
        move_d = math.sqrt(dx * dx + dy * dy + dz * dz)
        m = Move()
        m.accel = self.max_accel
        m.junction_deviation = self.junction_deviation
        if move_d < 0.000000001:
            if not de:
                return
            dx = dy = dz = 0.0
            move_d = abs(de)
            m.accel = 99999999.9
            velocity = speed
            m.is_kinematic_move = False
        else:
            velocity = min(speed, self.max_velocity)
            m.is_kinematic_move = True
        inv_move_d = 1.0 / move_d
        er = de * inv_move_d
        m.axes_d = (dx, dy, dz, de)
        m.axes_r = (dx * inv_move_d, dy * inv_move_d, dz * inv_move_d, er)
        m.move_d = move_d
        m.min_move_t = move_d / velocity
        m.max_start_v2 = 0.0
        m.max_cruise_v2 = velocity * velocity
        m.delta_v2 = 2.0 * move_d * m.accel
        m.next_junction_v2 = 999999999.9
        m.max_mcr_start_v2 = 0.0
        m.mcr_delta_v2 = 2.0 * move_d * self.mcr_pseudo_accel
        if dz and m.is_kinematic_move:
            z_ratio = move_d / abs(dz)
            m.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
        filament = 0.0
        if de:
            if (not dx and not dy) or er < 0.0:
                if abs(de) > self.max_e_dist:
                    raise self._error(
                        f"extrude-only move too long ({de:.3f} mm vs "
                        f"{self.max_e_dist:.3f} mm, max_extrude_only_distance)")
                inv_extrude_r = 1.0 / abs(er)
                m.limit_speed(self.max_e_velocity * inv_extrude_r,
                              self.max_e_accel * inv_extrude_r)
            elif er > self.max_extrude_ratio and \
                    de > self.limits.nozzle_diameter * self.max_extrude_ratio:
                raise self._error(
                    f"move exceeds maximum extrusion ({er * self.area:.3f} mm^2 vs"
                    f" {self.max_extrude_ratio * self.area:.3f} mm^2,"
                    " max_extrude_cross_section)")
            if de < 0.0:
                self.retracted_mm -= de
            else:
                refill = min(de, self.retracted_mm)
                self.retracted_mm -= refill
                filament = de - refill
        m.filament_mm = filament
        m.flow_per_mm = filament * self.area * inv_move_d
        m.offset = self._offset
        if m.is_kinematic_move:
            self.commanded_pos = list(newpos)
        else:
            self.commanded_pos = [start[0], start[1], start[2], newpos[3]]
        self.queue_move(m)

    # The two seams a bulk planner overrides (bulk_planner queues the moves
    # in its own array lookahead and flushes that one).
    def queue_move(self, m: Move) -> None:
        """A new move into the lookahead."""
        if self.lookahead.add_move(m, self.instant_corner_v):
            self._emit(self.lookahead.flush(lazy=True))

    def flush_queue(self) -> None:
        """Flush the whole lookahead (a G4, M400 or barrier)."""
        self._emit(self.lookahead.flush())
        self.lookahead.junction_flush = BUFFER_TIME_HIGH

    def _emit(self, moves: List[Move]) -> None:
        out = self._out
        t = self.print_time
        for m in moves:
            duration = m.accel_t + m.cruise_t + m.decel_t
            k = m.flow_per_mm
            out.append(Segment(t, duration, m.cruise_v * k, m.accel_t, m.decel_t,
                               m.start_v * k, m.end_v * k, m.cruise_v, m.move_d,
                               m.filament_mm, m.offset))
            t += duration
        self.print_time = t

    # --- firmware_retraction ----------------------------------------------------

    def _retract_move(self, length: float, speed: float) -> None:
        """G1 E<length> F<speed*60> in G91, between SAVE/RESTORE_GCODE_STATE."""
        saved_speed, saved_e = self.speed, self.last_position[3]
        saved_coord = self.absolute_coord
        self.absolute_coord = False
        try:
            self._g1({"E": length, "F": float(int(speed * 60))})
        finally:
            self.absolute_coord = saved_coord
            self.speed = saved_speed
        # RESTORE_GCODE_STATE keeps the G-code E position where it was.
        self.base_position[3] += self.last_position[3] - saved_e

    def _g10(self, args) -> None:
        if not self.is_retracted:
            self._retract_move(-self.retract_length, self.retract_speed)
            self.is_retracted = True

    def _g11(self, args) -> None:
        if self.is_retracted:
            self._retract_move(self.retract_length + self.unretract_extra_length,
                               self.unretract_speed)
            self.is_retracted = False

    def _set_retraction(self, args) -> None:
        params = self._extended()
        for key, attr, low in (
                ("RETRACT_LENGTH", "retract_length", 0.0),
                ("RETRACT_SPEED", "retract_speed", 1.0),
                ("UNRETRACT_EXTRA_LENGTH", "unretract_extra_length", 0.0),
                ("UNRETRACT_SPEED", "unretract_speed", 1.0)):
            if key in params:
                if params[key] < low:
                    raise self._error(f"{key} must be >= {low:g}")
                setattr(self, attr, params[key])
        self.is_retracted = False

    # --- gcode_arcs -----------------------------------------------------------------

    def _arc(self, args, clockwise: bool) -> None:
        if not self.absolute_coord:
            raise self._error("G2/G3 does not support relative move mode")
        params = self._floats(args, "XYZEF")
        other = self._floats(args, "IJKR")
        if "R" in other:
            raise self._error("G2/G3 does not support R moves")
        alpha, beta, _ = self.arc_axes
        names = "IJK"
        planar = (other.get(names[alpha], 0.0), other.get(names[beta], 0.0))
        if not (planar[0] or planar[1]):
            raise self._error("G2/G3 requires IJ, IK or JK parameters")
        current = gcode_position(self.last_position, self.base_position,
                                 self.extrude_factor)
        ends, extruded = arc_segments(current, params, planar, self.arc_axes,
                                      clockwise, self.absolute_extrude,
                                      self.limits.arc_resolution)
        for k, c in enumerate(ends):
            g1 = {"X": c[0], "Y": c[1], "Z": c[2]}
            if extruded is not None:
                g1["E"] = extruded[k]
            if "F" in params:
                g1["F"] = params["F"]
            self._g1(g1)

    _handlers = {
        "G0": lambda self, args: self._g1(self._floats(args, "XYZEF")),
        "G1": lambda self, args: self._g1(self._floats(args, "XYZEF")),
        "G2": lambda self, args: self._arc(args, True),
        "G3": lambda self, args: self._arc(args, False),
        "G4": _g4,
        "G10": _g10,
        "G11": _g11,
        "G17": lambda self, args: setattr(self, "arc_axes", (0, 1, 2)),
        "G18": lambda self, args: setattr(self, "arc_axes", (0, 2, 1)),
        "G19": lambda self, args: setattr(self, "arc_axes", (1, 2, 0)),
        "G20": _g20,
        "G28": _g28,
        "G90": lambda self, args: setattr(self, "absolute_coord", True),
        "G91": lambda self, args: setattr(self, "absolute_coord", False),
        "G92": _g92,
        "M82": lambda self, args: setattr(self, "absolute_extrude", True),
        "M83": lambda self, args: setattr(self, "absolute_extrude", False),
        "M204": _m204,
        "M220": _m220,
        "M221": _m221,
        "M400": _m400,
        "SET_VELOCITY_LIMIT": _set_velocity_limit,
        "SET_RETRACTION": _set_retraction,
    }


# Every command the reference acts on (the rest move nothing and are ignored)
HANDLED_COMMANDS = frozenset(Planner._handlers)


def plan_file(f: BinaryIO, limits: PrinterLimits = PrinterLimits()) -> Iterator[Event]:
    """Segments and barriers of a G-code file (opened in binary), in print time."""
    planner = Planner(limits)
    line = planner.line
    offset = 0
    for number, raw in enumerate(f, 1):
        events = line(raw, offset, number)
        if events:
            yield from events
        offset += len(raw)
    yield from planner.finish()


def plan_text(text: str, limits: PrinterLimits = PrinterLimits()) -> List[Event]:
    """All events of G-code given as text (tests, small snippets)."""
    return list(plan_file(io.BytesIO(text.encode()), limits))


def gcode_position(last_position: List[float], base_position: List[float],
                   extrude_factor: float) -> List[float]:
    """gcode_move's G-code position (X Y Z, E in G-code units) from its
    position and origin, as gcode_arcs reads it."""
    pos = [lp - bp for lp, bp in zip(last_position[:4], base_position[:4])]
    pos[3] /= extrude_factor
    return pos


def arc_segments(current: List[float], params: Dict[str, float],
                 planar: Tuple[float, float], arc_axes: Tuple[int, int, int],
                 clockwise: bool, absolute_extrude: bool, resolution: float
                 ) -> Tuple[List[Tuple[float, float, float]], Optional[List[float]]]:
    """gcode_arcs' segments of one G2 (clockwise) or G3, from the G-code
    position before it (current: X Y Z and E, E in G-code units), its X Y Z
    E words (params; F is the caller's) and its offsets to the centre in
    the arc's plane (planar, not both 0): each segment's end (X Y Z) and,
    if the arc extrudes, each one's E word; the same floats, in the same
    order, as klippy/extras/gcode_arcs.py computes them. The reference
    planner and the bulk planner both expand arcs with it."""
    target = [params.get(a, current[i]) for i, a in enumerate("XYZ")]
    alpha, beta, helical = arc_axes
    r_p, r_q = -planar[0], -planar[1]
    center_p = current[alpha] - r_p
    center_q = current[beta] - r_q
    rt_alpha = target[alpha] - center_p
    rt_beta = target[beta] - center_q
    angular_travel = math.atan2(r_p * rt_beta - r_q * rt_alpha,
                                r_p * rt_alpha + r_q * rt_beta)
    if angular_travel < 0.0:
        angular_travel += 2.0 * math.pi
    if clockwise:
        angular_travel -= 2.0 * math.pi
    if (angular_travel == 0.0 and current[alpha] == target[alpha]
            and current[beta] == target[beta]):
        angular_travel = 2.0 * math.pi
    linear_travel = target[helical] - current[helical]
    radius = math.hypot(r_p, r_q)
    flat_mm = radius * angular_travel
    mm_of_travel = math.hypot(flat_mm, linear_travel) if linear_travel \
        else math.fabs(flat_mm)
    segments = max(1.0, math.floor(mm_of_travel / resolution))
    theta_per_segment = angular_travel / segments
    linear_per_segment = linear_travel / segments
    e_per_move = e_base = 0.0
    if "E" in params:
        if absolute_extrude:
            e_base = current[3]
        e_per_move = (params["E"] - e_base) / segments
    count = int(segments)
    p0, p1 = planar
    height = current[helical]
    cos, sin = math.cos, math.sin
    ends = []
    for i in range(1, count):
        c_theta = i * theta_per_segment
        cos_ti, sin_ti = cos(c_theta), sin(c_theta)
        # the end in the arc's plane (alpha, beta) and along its axis
        a = center_p + (-p0 * cos_ti + p1 * sin_ti)
        b = center_q + (-p0 * sin_ti - p1 * cos_ti)
        h = height + i * linear_per_segment
        if alpha == 0 and beta == 1:
            ends.append((a, b, h))
        else:
            c = [0.0, 0.0, 0.0]
            c[alpha], c[beta], c[helical] = a, b, h
            ends.append(tuple(c))
    ends.append(tuple(target))
    if not e_per_move:
        return ends, None
    if not absolute_extrude:
        return ends, [e_base + e_per_move] * count
    extruded = []
    for _ in range(count):
        extruded.append(e_base + e_per_move)
        e_base += e_per_move
    return ends, extruded
