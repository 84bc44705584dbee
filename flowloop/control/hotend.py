"""The hotend thermal model: where the nozzle temperature really is.

An energy balance of the heater block (the one Kalico's control_mpc and
Marlin's MPC use), with a heater controller that makes it follow its target
as a first-order lag after a dead time:

    C dT/dt = P - (k_loss + c_fil * flow) * (T - T_ambient)
    P = clamp(P_hold + C / tau * (T_target(t - dead_time) - T), 0, max_power)

where P_hold = (k_loss + c_fil * flow) * (T - T_ambient) is the power that
holds the temperature. While P stays within 0..max_power the nozzle follows
its target exactly as a first-order lag (tau) after the dead time; when the
filament's heat (c_fil * flow, the cooling that extrusion itself causes)
plus the loss to the room need more than the heater has, P clamps at
max_power and the nozzle sags. The defaults are a 40 W cartridge in a
V6-like block (Marlin's MPC defaults: 16.7 J/K block, 0.07 W/K to the room)
and PLA (0.0056 J/K per mm of 1.75 mm filament = 0.00233 J/K/mm^3).

The same model is the simulated twin's hotend and the limiter's estimate of
the nozzle temperature where no reading exists (klippy batch mode).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Deque, Optional, Tuple

from ..errors import FlowloopError

# Integration step: well below tau and the block's own time constant.
STEP_S = 0.05
# Times this close are one instant: a clock summed step by step drifts, and
# without it a target change fell a step earlier or later depending on how
# the model was advanced (in one call or several), 0.06 C apart on a ramp.
SAME_INSTANT_S = 1e-9


@dataclass(frozen=True)
class HotendParams:
    heat_capacity_j_per_c: float = 16.7
    max_power_w: float = 40.0
    loss_w_per_c: float = 0.07
    filament_j_per_mm3_c: float = 0.00233
    time_constant_s: float = 4.0
    dead_time_s: float = 1.0
    ambient_c: float = 25.0

    def __post_init__(self):
        for name in ("heat_capacity_j_per_c", "max_power_w", "time_constant_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise FlowloopError(f"{name} must be above 0, not {value}")
        for name in ("loss_w_per_c", "filament_j_per_mm3_c", "dead_time_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise FlowloopError(f"{name} must be >= 0, not {value}")

    def steady_power_w(self, temp_c: float, flow_mm3_s: float) -> float:
        """Power that holds temp_c while extruding flow_mm3_s."""
        k = self.loss_w_per_c + self.filament_j_per_mm3_c * max(0.0, flow_mm3_s)
        return k * (temp_c - self.ambient_c)

    def max_steady_flow_mm3_s(self, temp_c: float) -> float:
        """The most flow the heater can hold temp_c at (inf at ambient)."""
        rise = temp_c - self.ambient_c
        if rise <= 0.0 or self.filament_j_per_mm3_c == 0.0:
            return math.inf
        spare = self.max_power_w - self.loss_w_per_c * rise
        return max(0.0, spare / (self.filament_j_per_mm3_c * rise))


class HotendModel:
    """Nozzle temperature over print time, given targets and extrusion flow."""

    def __init__(self, params: HotendParams = HotendParams(),
                 temp_c: Optional[float] = None, time_s: float = 0.0,
                 target_c: float = 0.0):
        self.params = params
        self.temp_c = params.ambient_c if temp_c is None else float(temp_c)
        self.time_s = float(time_s)
        self.power_w = 0.0
        # Set: the heater holds this power, no controller (a fixed-power
        # measurement); the temperature then settles where loss meets it.
        self.fixed_power_w: Optional[float] = None
        # (time the target was set, target): the controller sees each one
        # dead_time_s later.
        self._targets: Deque[Tuple[float, float]] = collections.deque(
            [(-math.inf, float(target_c))])

    def set_target(self, time_s: float, target_c: float) -> None:
        if target_c != self._targets[-1][1]:
            self._targets.append((max(time_s, self._targets[-1][0]), target_c))

    def target_seen_at(self, time_s: float) -> float:
        """The target the controller acts on at time_s (after dead time)."""
        seen = time_s - self.params.dead_time_s + SAME_INSTANT_S
        targets = self._targets
        while len(targets) > 1 and targets[1][0] <= seen:
            targets.popleft()
        return targets[0][1]

    def advance(self, until_s: float, flow_mm3_s: float = 0.0) -> float:
        """Run the model to until_s at a steady flow; returns the temperature.

        In steps of STEP_S, each in closed form. Called once per G-code move
        (the limiter in batch mode) and per sample (the twin), so the steps
        that keep the heater on one side (within its limits, or clamped at
        one) and see one target are taken as one closed-form step: the
        power is linear in the temperature, which moves monotonically, so
        both ends on one side means every step between is. The clock still
        counts every step, so target changes and the last step fall where
        single steps put them."""
        p = self.params
        flow = max(0.0, flow_mm3_s)
        k = p.loss_w_per_c + p.filament_j_per_mm3_c * flow
        targets = self._targets
        temp, time_s, power = self.temp_c, self.time_s, self.power_w
        target = self.target_seen_at(time_s)
        next_change = targets[1][0] if len(targets) > 1 else math.inf
        # Whole steps before the last one and before the next target change
        steps = int(min(until_s - time_s,
                        next_change + p.dead_time_s - time_s) / STEP_S
                    + SAME_INSTANT_S) - 1
        if steps >= 2:
            power, lag = self._power(temp, target, k)
            after = self._after(temp, target, power, lag, k, steps * STEP_S)
            end_power, end_lag = self._power(after, target, k)
            if end_lag if lag else (not end_lag and end_power == power):
                temp = after
                for _ in range(steps):
                    time_s += STEP_S
        while time_s < until_s:
            dt = min(STEP_S, until_s - time_s)
            if next_change <= time_s - p.dead_time_s + SAME_INSTANT_S:
                target = self.target_seen_at(time_s)
                next_change = targets[1][0] if len(targets) > 1 else math.inf
            power, lag = self._power(temp, target, k)
            temp = self._after(temp, target, power, lag, k, dt)
            time_s += dt
        self.temp_c, self.time_s, self.power_w = temp, time_s, power
        return temp

    def _power(self, temp_c: float, target_c: float,
               k: float) -> Tuple[float, bool]:
        """The heater's power at temp_c, and whether it is within the
        heater's limits (then the nozzle follows its target as a lag)."""
        p = self.params
        fixed = self.fixed_power_w
        if fixed is not None:
            power = fixed
        elif target_c <= 0.0:
            power = 0.0  # heater off
        else:
            drive = p.heat_capacity_j_per_c / p.time_constant_s
            power = k * (temp_c - p.ambient_c) + drive * (target_c - temp_c)
        power = min(p.max_power_w, max(0.0, power))
        return power, (0.0 < power < p.max_power_w and target_c > 0.0
                       and fixed is None)

    def _after(self, temp_c: float, target_c: float, power: float, lag: bool,
               k: float, dt: float) -> float:
        """The temperature dt later, on the same side of the heater's limits."""
        p = self.params
        if lag:
            # Within the heater's limits: the exact first-order lag step.
            return target_c + (temp_c - target_c) * math.exp(
                -dt / p.time_constant_s)
        if k > 0:
            # Clamped power: the block's own exponential toward balance.
            balance = p.ambient_c + power / k
            return balance + (temp_c - balance) * math.exp(
                -dt * k / p.heat_capacity_j_per_c)
        return temp_c + power * dt / p.heat_capacity_j_per_c


# A new estimate as often as Klipper's thermistors report (adc_temperature's
# REPORT_TIME): the caps see what they would on a printer.
READING_PERIOD_S = 0.3


class NozzleEstimate:
    """The nozzle temperature where no reading exists (klippy batch mode):
    the hotend model run on the moves' own time. Moves only add up their
    time and melted plastic; every READING_PERIOD_S of it the model runs
    once at their mean flow, so the cost is per reading, not per move."""

    def __init__(self, model: Optional[HotendModel] = None):
        self.model = HotendModel() if model is None else model
        self._pending_s = 0.0
        self._pending_mm3 = 0.0

    def add_move(self, duration_s: float, melted_mm3: float) -> bool:
        """One move's time and the plastic it melted; True when a reading
        is due (call `read`)."""
        self._pending_s += duration_s
        self._pending_mm3 += melted_mm3
        return self._pending_s >= READING_PERIOD_S

    def read(self, target_c: float) -> float:
        """Run the model over the moves added, with the heater's target now."""
        model = self.model
        model.set_target(model.time_s, target_c)
        pending_s, self._pending_s = self._pending_s, 0.0
        melted, self._pending_mm3 = self._pending_mm3, 0.0
        if pending_s <= 0.0:
            return model.temp_c
        return model.advance(model.time_s + pending_s, melted / pending_s)


def heater_reads(writes_to_file: bool, estimated_print_time_s: float) -> bool:
    """Whether the heater's temperature readings arrive: not in klippy's
    batch mode (its output is a file and its MCU clock never starts: the
    heater reads 0 C); on a printer, and in a klippy paced to the clock,
    whose simulated twin gives the heater its readings."""
    return not (writes_to_file and not estimated_print_time_s)


def nozzle_estimate_for(writes_to_file: bool, estimated_print_time_s: float,
                        params: Optional[HotendParams] = None
                        ) -> Optional[NozzleEstimate]:
    """The estimate to read the nozzle from where no temperature reading
    arrives (heater_reads), on the hotend `params` describe (the default
    hotend's if None). None: the heater's own reading is used."""
    if heater_reads(writes_to_file, estimated_print_time_s):
        return None
    return NozzleEstimate(None if params is None else HotendModel(params))
