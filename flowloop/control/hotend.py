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
        seen = time_s - self.params.dead_time_s
        targets = self._targets
        while len(targets) > 1 and targets[1][0] <= seen:
            targets.popleft()
        return targets[0][1]

    def advance(self, until_s: float, flow_mm3_s: float = 0.0) -> float:
        """Run the model to until_s at a steady flow; returns the temperature."""
        p = self.params
        flow = max(0.0, flow_mm3_s)
        k = p.loss_w_per_c + p.filament_j_per_mm3_c * flow
        while self.time_s < until_s:
            dt = min(STEP_S, until_s - self.time_s)
            target = self.target_seen_at(self.time_s)
            rise = self.temp_c - p.ambient_c
            hold = k * rise
            fixed = self.fixed_power_w
            if fixed is not None:
                power = fixed
            elif target <= 0.0:
                power = 0.0  # heater off
            else:
                drive = p.heat_capacity_j_per_c / p.time_constant_s
                power = hold + drive * (target - self.temp_c)
            power = min(p.max_power_w, max(0.0, power))
            if 0.0 < power < p.max_power_w and target > 0.0 and fixed is None:
                # Within the heater's limits: the exact first-order lag step.
                self.temp_c = target + (self.temp_c - target) * math.exp(
                    -dt / p.time_constant_s)
            else:
                # Clamped power: the block's own exponential toward balance.
                balance = p.ambient_c + (power / k if k > 0 else 0.0)
                if k > 0:
                    self.temp_c = balance + (self.temp_c - balance) * math.exp(
                        -dt * k / p.heat_capacity_j_per_c)
                else:
                    self.temp_c += power * dt / p.heat_capacity_j_per_c
            self.power_w = power
            self.time_s += dt
        return self.temp_c
