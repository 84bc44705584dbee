"""The flowrate and temperature limiter: every cap, and the speed of a move.

`FlowLimiter` holds what the caps know (the fixed max_flow, the active
profile's melt line, the hotend temperature, the sensor's grip windows) and
answers one question per G-code move: at what speed may it run. The caps:

- max_flow: a fixed cap (mm^3/s), no sensor or profile needed;
- temperature: the active profile's melt line at the measured temperature;
- grip: the reactive rule (flowloop.control.reactive) after a slip;
- model: the predictive grip model (flowloop.control.grip_model): the flow at
  which it predicts the feeder starts to slip at the measured temperature.

The mode says which caps may act; each mode adds one to the one before:
static (max_flow), temperature, reactive, predictive. The lowest cap wins.
max_flow and temperature are hard caps; the grip caps never slow a move
below min_speed_factor of the speed the hard caps leave it. A cap that lacks
its input (no profile, no temperature) is off, and the status says why; a
sensor fault freezes the grip caps (never raising one): it reaches the
limiter by one path, the windows: those the sensor closes while faulted
say so (Window.faulted) and no rule judges them; every window carries the
fault's name (Window.fault), which only the status shows.

`limit` runs once per G-code move: what it needs (the lowest cap, the hard
one, the floor) is worked out when a cap changes, and a move under the
lowest cap returns at once. The status is a new dict whenever something in
it changes (a slowed move too), never built when read and never changed in
place: klippy's status poll keeps the dict it was handed and compares the
next one with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional

from ..errors import FlowloopError
from ..material.profile import (
    DEFAULT_WORKING_POINT,
    Line,
    Profile,
    min_grip_of,
    profile_line,
)
from ..window import Window
from . import caps as fl_caps
from .grip_model import (
    CLIMB_FROM,
    DEFAULT_FILAMENT_AREA_MM2,
    SLIP_TOLERANCE,
    CapacityLine,
    GripModel,
    judged_flow_mm3_s,
)
from .nozzle_health import PrintEvidence, melt_ratio_arg
from .reactive import (
    DEFAULT_HYSTERESIS,
    DEFAULT_MIN_GRIP,
    DEFAULT_MIN_SPEED_FACTOR,
    DEFAULT_RECOVERY_PER_S,
    ReactiveRule,
    ReactiveSettings,
    check_min_grip,
)

MODES = ("static", "temperature", "reactive", "predictive")
DEFAULT_MODE = "predictive"
MODE_CAPS = {mode: fl_caps.CAP_NAMES[:i + 1] for i, mode in enumerate(MODES)}
# A temperature change smaller than this does not recompute the caps.
TEMP_RESOLUTION_C = 0.1
# A carried seed (set_profile's melt_ratio) no window has confirmed (by a
# slip beyond SLIP_TOLERANCE) after moves ran this long under the model's
# cap is dropped: capped there they never slip, so a seed too low (a new
# nozzle after a worn one) would otherwise never show the hotend melts more.
# A seed at or a little above the hotend's capacity is confirmed within
# seconds (the model's belief sits 1-5 % above it).
CONFIRM_SEED_S = 30.0
# A carried seed starts this far above the ratio given: a model's belief at
# a print's end may sit within the noise band above the hotend, where no
# capped window slips enough to confirm it (the bench's worn nozzle, 0.6 %
# above, was dropped); a little higher, the first capped windows slip just
# beyond the band and confirm or correct it.
SEED_PROBE = SLIP_TOLERANCE


def check_mode(value: str) -> str:
    mode = str(value).strip().lower()
    if mode not in MODES:
        raise FlowloopError(f"mode must be one of {', '.join(MODES)}, not {value!r}")
    return mode


def check_climb_from(value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not 0.0 < value <= 1.0:
        raise FlowloopError(f"climb_from must be in (0, 1], not {value!r}")
    return float(value)


def check_min_speed_factor(value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not 0.0 < value <= 1.0:
        raise FlowloopError(f"min_speed_factor must be in (0, 1], not {value!r}")
    return float(value)


@dataclass(frozen=True)
class LimiterSettings:
    max_flow_mm3_s: Optional[float] = None
    mode: str = DEFAULT_MODE
    min_grip: Optional[float] = None  # None: the profile's, else DEFAULT_MIN_GRIP
    min_speed_factor: float = DEFAULT_MIN_SPEED_FACTOR
    hysteresis: float = DEFAULT_HYSTERESIS
    recovery_per_s: float = DEFAULT_RECOVERY_PER_S
    # a first print's model climbs from this share of the profile's capacity
    # (flowloop.control.grip_model.CLIMB_FROM; 1: it starts at the line)
    climb_from: float = CLIMB_FROM

    def __post_init__(self):
        if self.max_flow_mm3_s is not None:
            fl_caps.check_max_flow(self.max_flow_mm3_s)
        object.__setattr__(self, "mode", check_mode(self.mode))
        if self.min_grip is not None:
            check_min_grip(self.min_grip)
        check_min_speed_factor(self.min_speed_factor)
        check_climb_from(self.climb_from)
        ReactiveSettings(DEFAULT_MIN_GRIP, self.hysteresis, self.recovery_per_s)


class FlowLimiter:
    def __init__(self, settings: LimiterSettings = LimiterSettings(),
                 filament_area_mm2: float = DEFAULT_FILAMENT_AREA_MM2,
                 host: Optional[Dict[str, Any]] = None):
        self.settings = settings
        self.filament_area_mm2 = filament_area_mm2
        self.host = host  # the klippy it runs in (status 'host'), if known
        self.enabled = True
        self.profile: Optional[Profile] = None
        self.working_point = DEFAULT_WORKING_POINT
        self.model: Optional[GripModel] = None
        # what the model was seeded with: this hotend's melt ratio against
        # the profile from its earlier prints (None: the profile's line)
        self.seed_melt_ratio: Optional[float] = None
        # the carried ratio dropped unconfirmed (None: none dropped), and
        # the time moves ran under the model's cap while a carried seed was
        # unconfirmed (None: no such seed)
        self.dropped_melt_ratio: Optional[float] = None
        self._unconfirmed_s: Optional[float] = None
        # what the windows say of the hotend against the active profile
        # (flowloop.control.nozzle_health), summed since it was activated
        self.evidence: Optional[PrintEvidence] = None
        self._line: Optional[Line] = None
        # the model's seed had the hotend melted what the profile says
        self._profile_capacity: Optional[CapacityLine] = None
        self.temp_c: Optional[float] = None
        self.sensor_fault: Optional[str] = None
        self.reactive = self._reactive_rule()
        self.caps: Dict[str, Optional[float]] = {}
        self.active = fl_caps.ActiveCap(None, "none")
        # For limit(): the lowest cap in force (None: none), the lowest hard
        # one, and whether the grip floor applies
        self._cap_mm3_s: Optional[float] = None
        self._hard_cap_mm3_s: Optional[float] = None
        self._grip_capped = False
        self.why = ""
        self.slowed_time_s = 0.0
        self.slowed_moves = 0
        # What the sensor saw, limiter on or off: judged windows, and those
        # below min_grip
        self.windows_judged = 0
        self.windows_below_min_grip = 0
        self._status: Dict[str, Any] = {}
        self._update()

    # --- inputs ------------------------------------------------------------
    @property
    def min_grip(self) -> float:
        return min_grip_of(self.profile, self.settings.min_grip)

    def _reactive_rule(self) -> ReactiveRule:
        s = self.settings
        return ReactiveRule(
            ReactiveSettings(self.min_grip, s.hysteresis, s.recovery_per_s),
            self.filament_area_mm2)

    def configure(self, enabled: Optional[bool] = None,
                  max_flow_mm3_s: Optional[float] = None, clear_max_flow=False,
                  mode: Optional[str] = None) -> None:
        """Change what SET_FLOWRATE_LIMIT may change; checks everything first,
        so bad input changes nothing."""
        changes: Dict[str, Any] = {}
        if max_flow_mm3_s is not None:
            changes["max_flow_mm3_s"] = fl_caps.check_max_flow(max_flow_mm3_s,
                                                               "MAX_FLOW")
        elif clear_max_flow:
            changes["max_flow_mm3_s"] = None
        if mode is not None:
            changes["mode"] = check_mode(mode)
        settings = LimiterSettings(**{**self.settings.__dict__, **changes})
        self.settings = settings
        if enabled is not None:
            self.enabled = bool(enabled)
        self._update()

    def set_profile(self, profile: Optional[Profile],
                    working_point: float = DEFAULT_WORKING_POINT,
                    melt_ratio: Optional[float] = None) -> None:
        """A newly active profile (None: none) seeds the temperature cap and
        a fresh grip model: the profile's melt line, times melt_ratio when
        given (what this hotend melted against the profile in its earlier
        prints: nozzle_health.carried_ratio, which Moonraker sends with the
        activation), SEED_PROBE above it, until the windows confirm it
        (CONFIRM_SEED_S). Checks the ratio first: a bad one changes nothing.
        The temperature cap stays the profile's: the ratio seeds only what
        the windows correct."""
        if melt_ratio is not None:
            melt_ratio = melt_ratio_arg(melt_ratio)
        self.profile = profile
        self.working_point = working_point
        self.model = None
        self.evidence = None
        self.seed_melt_ratio = self.dropped_melt_ratio = None
        self._unconfirmed_s = None
        if profile is not None:
            line = profile_line(profile, working_point)
            seed_grip = min_grip_of(profile)
            self._line = line
            self.seed_melt_ratio = melt_ratio
            self._unconfirmed_s = None if melt_ratio is None else 0.0
            self.evidence = PrintEvidence(profile.name, working_point, seed_grip)
            self._profile_capacity = CapacityLine.from_profile_line(
                line, seed_grip, profile.bounds.recommended_temp_c)
            self.model = GripModel(CapacityLine.from_profile_line(
                line, seed_grip, profile.bounds.recommended_temp_c,
                1.0 if melt_ratio is None
                else melt_ratio * (1.0 + SEED_PROBE)),
                filament_area_mm2=self.filament_area_mm2,
                climb_from=self.settings.climb_from if melt_ratio is None
                else None)
        self.reactive = self._reactive_rule()
        self._update()

    def _drop_seed(self) -> None:
        """The carried seed went unconfirmed: capped there nothing slipped,
        so the hotend melts at least that much. The model climbs from it to
        the profile's line, as a first print climbs from climb_from (its
        windows decide from here). The move being capped keeps its speed;
        later ones get the new caps."""
        below = min(1.0, self.model.ratio_to(self._profile_capacity))
        self.dropped_melt_ratio, self.seed_melt_ratio = self.seed_melt_ratio, None
        self._unconfirmed_s = None
        self.model = GripModel(self._profile_capacity,
                               filament_area_mm2=self.filament_area_mm2,
                               climb_from=below)
        self._update()

    @property
    def model_melt_ratio(self) -> Optional[float]:
        """What the grip model believes the hotend melts against the
        profile (nozzle health's ratio: its capacity over the profile's
        line at min_grip), None without a profile."""
        if self.model is None:
            return None
        return self.model.ratio_to(self._profile_capacity)

    @property
    def measured_melt_ratio(self) -> Optional[float]:
        """model_melt_ratio once the windows have measured the hotend: None
        while a first print's model still climbs (it knows only that the
        hotend melts at least that much), which is what the next print is
        seeded with (flowrate_limiter/nozzle_evidence: nozzle health carries
        it)."""
        if self.model is None or self.model.climb_ratio is not None:
            return None
        return self.model_melt_ratio

    def set_temperature(self, temp_c: Optional[float]) -> None:
        temp_c = None if temp_c is None else float(temp_c)
        old = self.temp_c
        if temp_c is None or old is None \
                or abs(temp_c - old) >= TEMP_RESOLUTION_C:
            self.temp_c = temp_c
            if temp_c != old:
                self._update()

    def on_window(self, window: Window) -> None:
        """One closed grip window of the sensor, as it delivered it. A
        faulted one is never judged, so the grip caps neither lower (a dead
        sensor is not a slip) nor recover (nothing shows the hotend keeps
        up): a cap in force stays, so a fault never raises one. Its fault's
        name is for the status only."""
        if window.fault != self.sensor_fault:
            self.sensor_fault = window.fault
            self._update()
        if self.evidence is not None and self._line is not None:
            self.evidence.add(window, self._line, self.filament_area_mm2)
        if judged_flow_mm3_s(window, self.filament_area_mm2) is None:
            return  # faulted, not judged, or no forward flow: nothing to judge
        self.windows_judged += 1
        if float(window.grip) < self.min_grip:
            self.windows_below_min_grip += 1
        self._status = {**self._status, "grip_windows": self._grip_windows()}
        before = self.reactive.cap_mm3_s
        self.reactive.on_window(window)
        learned = self.model is not None and self.model.learn(window)
        if learned and float(window.grip) < 1.0 - SLIP_TOLERANCE:
            # a real slip: the hotend melts no more than about the seed (a
            # window that slipped within the noise confirms nothing: at a
            # seed too low they come too, from the nozzle's temperature
            # moving under the cap)
            self._unconfirmed_s = None
        if learned or self.reactive.cap_mm3_s != before:
            self._update()

    # --- the decision --------------------------------------------------------
    def _update(self) -> None:
        allowed = MODE_CAPS[self.settings.mode]
        caps: Dict[str, Optional[float]] = dict.fromkeys(fl_caps.CAP_NAMES)
        why = []
        caps["max_flow"] = self.settings.max_flow_mm3_s
        if self.profile is None:
            why.append("no active profile: temperature and model caps off")
        elif self.temp_c is None:
            why.append("no hotend temperature: temperature and model caps off")
        else:
            temp = min(self.temp_c, self.profile.bounds.max_temp_c)
            caps["temperature"] = profile_line(
                self.profile, self.working_point).flow_mm3_s(temp)
            if self.model is not None:
                caps["model"] = self.model.cap_mm3_s(temp)
        if self.sensor_fault is not None:
            why.append(f"sensor fault '{self.sensor_fault}': grip caps frozen")
        caps["grip"] = self.reactive.cap_mm3_s
        self.caps = {name: (round(v, 4) if v is not None and name in allowed
                            else None) for name, v in caps.items()}
        self.active = fl_caps.lowest_cap(**self.caps) if self.enabled \
            else fl_caps.ActiveCap(None, "none")
        self._cap_mm3_s = self.active.cap_mm3_s
        hard = [c for c in (self.caps["max_flow"], self.caps["temperature"])
                if c is not None]
        self._hard_cap_mm3_s = min(hard) if hard else None
        self._grip_capped = self.active.reason in ("grip", "model")
        if not self.enabled:
            why.insert(0, "disabled")
        self.why = "; ".join(why)
        self._build_status()

    def pieces(self, shape: fl_caps.MoveShape, speed_mm_s: float) -> int:
        """How many pieces to queue a move in, where the caps can change
        while it waits to run: an extruding move longer than
        fl_caps.CUT_FROM_S in pieces of at most fl_caps.PIECE_S, whenever a
        cap that follows the hotend (its temperature, the grip, the model)
        may act. 1: queue it whole."""
        if not self.enabled or "temperature" not in MODE_CAPS[self.settings.mode]:
            return 1  # off, or max_flow alone (static): no cap moves
        return fl_caps.piece_count(shape, speed_mm_s)

    def limit(self, shape: fl_caps.MoveShape, speed_mm_s: float) -> float:
        """The speed this move may run at (never above speed_mm_s)."""
        cap = self._cap_mm3_s
        if cap is None or shape.extrude_mm <= 0.0 or shape.flow_mm3_s(
                speed_mm_s, self.filament_area_mm2) <= cap:
            return speed_mm_s  # under the lowest cap: no cap slows it
        speed = fl_caps.capped_speed(shape, speed_mm_s, self._hard_cap_mm3_s,
                                     self.filament_area_mm2)
        if self._grip_capped:
            # The floor is a share of the speed the hard caps leave
            speed = fl_caps.capped_speed(
                shape, speed, cap, self.filament_area_mm2,
                floor_mm_s=self.settings.min_speed_factor * speed)
        if speed < speed_mm_s:
            if self._unconfirmed_s is not None and self.active.reason == "model":
                self._unconfirmed_s += shape.duration_s(speed)
                if self._unconfirmed_s >= CONFIRM_SEED_S:
                    self._drop_seed()
            self.slowed_moves += 1
            self.slowed_time_s += shape.duration_s(speed) - shape.duration_s(
                speed_mm_s)
            self._status = {**self._status, "slowed_moves": self.slowed_moves,
                            "slowed_time": round(self.slowed_time_s, 3)}
        return speed

    # --- status --------------------------------------------------------------
    def _build_status(self) -> None:
        cap = self.active.cap_mm3_s
        self._status = {
            "enabled": self.enabled,
            "mode": self.settings.mode,
            "max_flow": self.settings.max_flow_mm3_s,
            "cap": None if cap is None else round(cap, 3),
            "reason": self.active.reason,
            "why": self.why,
            "caps": dict(self.caps),
            "min_grip": self.min_grip,
            "temperature": None if self.temp_c is None else round(self.temp_c, 1),
            "profile": None if self.profile is None else self.profile.name,
            "slowed_time": round(self.slowed_time_s, 3),
            "slowed_moves": self.slowed_moves,
            "model": None if self.model is None else {
                **self.model.status(),
                "melt_ratio": round(self.model_melt_ratio, 4)},
            "seed_melt_ratio": self.seed_melt_ratio,
            "dropped_melt_ratio": self.dropped_melt_ratio,
            "grip_windows": self._grip_windows(),
            "host": self.host,
        }

    def _grip_windows(self) -> Dict[str, int]:
        return {"judged": self.windows_judged,
                "below_min_grip": self.windows_below_min_grip}

    def status(self) -> Dict[str, Any]:
        """The held status: a new dict after every change, never changed in
        place (hand it out as it is)."""
        return self._status


def status_line(section: str, s: Dict[str, Any]) -> str:
    """QUERY_FLOWRATE_LIMIT's answer: a limiter's status (FlowLimiter.status)
    on one line."""
    cap = "none" if s["cap"] is None else f"{s['cap']:.2f} mm^3/s"
    caps = ", ".join(f"{name} {'off' if v is None else f'{v:.2f}'}"
                     for name, v in s["caps"].items())
    state = "enabled" if s["enabled"] else "disabled"
    model = s["model"] or {}
    return (f"{section}: {state}, mode {s['mode']}, cap {cap}"
            f" ({s['reason']}); caps: {caps}; slowed {s['slowed_moves']} moves"
            f" by {s['slowed_time']:.1f} s"
            + (f"; model seeded at melt ratio {s['seed_melt_ratio']:.2f}"
               if s["seed_melt_ratio"] is not None else "")
            + (f"; model climbing, at {model['climb_ratio']:.2f} of the"
               " profile's capacity"
               if model.get("climb_ratio") is not None else "")
            + (f"; carried melt ratio {s['dropped_melt_ratio']:.2f} dropped"
               " unconfirmed" if s["dropped_melt_ratio"] is not None else "")
            + (f"; {s['why']}" if s["why"] else ""))
