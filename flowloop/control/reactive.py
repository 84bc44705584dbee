"""The reactive grip rule: slow down after the feeder slipped, recover slowly.

The rule is stated in speed. When a judged grip window reads grip g below
`min_grip`, the feeder moved only g of the filament it was told to; the
hotend melted what it could while asked for more: g * F for a window at
one flow F, and for a window that mixed flows the capacity its commanded
flow over time gives (grip_model.WindowFlow). The cap drops to that flow,
so the next moves ask for what the hotend just proved it can melt (never
below `min_speed_factor` of the speed they would run at without the grip
caps; that floor is applied per move by the limiter). A lower cap is
never raised by a slip.

Between `min_grip` and `min_grip + hysteresis` the cap holds. At or above it,
after a hold of good grip (RECOVERY_HOLD_S, doubled by every slip that comes
while the cap is still on, up to MAX_RECOVERY_HOLD_S), the cap rises by
`recovery_per_s` of the flow that slipped (the window's peak) per second
of good window: the speed of the moves that slipped climbs back by at most
that share of their G-code speed per second (0.2: from 0.5 to full speed
in 2.5 s), and the cap is released once it is back at the flow that
slipped. ddPrint's rule follows grip with no memory and no hysteresis, so
it oscillates around the slip point; this one reacts at once, returns
slowly, and backs off when the hotend stays weak.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from ..errors import FlowloopError
from ..material.profile import DEFAULT_MIN_GRIP
from ..window import Window
from .grip_model import (
    DEFAULT_FILAMENT_AREA_MM2,
    WindowFlow,
    duration_s,
    judged_flow_mm3_s,
)

DEFAULT_MIN_SPEED_FACTOR = 0.3
DEFAULT_HYSTERESIS = 0.03
DEFAULT_RECOVERY_PER_S = 0.2
# A window longer than this counts as this long for recovery (a pause is not
# evidence that the hotend keeps up).
MAX_RECOVERY_STEP_S = 1.0
# Good grip needed before the cap starts to rise, doubled per repeated slip.
RECOVERY_HOLD_S = 2.0
MAX_RECOVERY_HOLD_S = 30.0


def check_min_grip(value: float, what: str = "min_grip") -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool) \
            or not 0.0 < value <= 1.0:
        raise FlowloopError(f"{what} must be in (0, 1], not {value!r}")
    return float(value)


@dataclass(frozen=True)
class ReactiveSettings:
    min_grip: float = DEFAULT_MIN_GRIP
    hysteresis: float = DEFAULT_HYSTERESIS
    recovery_per_s: float = DEFAULT_RECOVERY_PER_S

    def __post_init__(self):
        check_min_grip(self.min_grip)
        if not 0.0 <= self.hysteresis < 1.0:
            raise FlowloopError(f"hysteresis must be in 0..1, not {self.hysteresis}")
        if not self.recovery_per_s > 0.0:
            raise FlowloopError(
                f"recovery_rate must be above 0, not {self.recovery_per_s}")


class ReactiveRule:
    def __init__(self, settings: ReactiveSettings = ReactiveSettings(),
                 filament_area_mm2: float = DEFAULT_FILAMENT_AREA_MM2):
        self.settings = settings
        self.filament_area_mm2 = filament_area_mm2
        self.cap_mm3_s: Optional[float] = None
        self.slip_flow_mm3_s: Optional[float] = None  # the flow that slipped
        self.hold_s = RECOVERY_HOLD_S
        self.good_s = 0.0  # good grip since the last slip

    def reset(self) -> None:
        self.cap_mm3_s = self.slip_flow_mm3_s = None
        self.hold_s = RECOVERY_HOLD_S
        self.good_s = 0.0

    def on_window(self, window: Window) -> Optional[float]:
        """Update from one closed grip window (one no rule may judge, a
        faulted one among them, changes nothing); returns the cap (mm^3/s)
        or None when the rule does not limit. A slip caps at what the
        hotend melted while asked for more, from the window's commanded
        flow over time (grip_model.WindowFlow), and recovers toward the
        flow that slipped (its peak)."""
        commanded = judged_flow_mm3_s(window, self.filament_area_mm2)
        if commanded is None:
            return self.cap_mm3_s
        grip = float(window.grip)
        s = self.settings
        if grip < s.min_grip:
            flow = WindowFlow.of(commanded, grip, window.commanded_flows)
            measured = flow.melted_mm3_s
            if self.cap_mm3_s is None:
                self.slip_flow_mm3_s = flow.peak_mm3_s
                self.cap_mm3_s = measured
            else:
                self.cap_mm3_s = min(self.cap_mm3_s, measured)
                if self.good_s > 0.0:  # slipped again on the way back
                    self.hold_s = min(2.0 * self.hold_s, MAX_RECOVERY_HOLD_S)
            self.good_s = 0.0
        elif grip >= s.min_grip + s.hysteresis and self.cap_mm3_s is not None:
            step = min(duration_s(window), MAX_RECOVERY_STEP_S)
            held = min(step, max(0.0, self.good_s + step - self.hold_s))
            self.good_s += step
            self.cap_mm3_s += s.recovery_per_s * held * self.slip_flow_mm3_s
            if self.cap_mm3_s >= self.slip_flow_mm3_s:
                self.reset()
        return self.cap_mm3_s

