"""The grip window: what the flow sensor says about a stretch of filament,
one frozen value from the sensor's pipeline to every rule that reads it
(the flowrate limiter's, the profile measurement's, the grip model's).

It lives at the bottom of the package (it imports nothing of flowloop) so
that flowloop.sensor, which makes windows, and flowloop.material and
flowloop.control, which judge them, import it downward.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

# Why a window has, or has no, grip
JUDGED = "judged"
RETRACTION = "retraction"          # the filament went back: nothing to judge
TOO_LITTLE_MOTION = "too_little_motion"
STUCK = "stuck"                    # the sensor did not move while fed
FAULT = "fault"                    # the sensor is faulted: never judged
REASONS = (JUDGED, RETRACTION, TOO_LITTLE_MOTION, STUCK, FAULT)


@dataclass(frozen=True)
class Window:
    """One closed grip window, as [flow_sensor]'s subscribers receive it."""
    start_time: float
    end_time: float
    commanded_mm: float
    measured_mm: float
    grip: Optional[float]
    reason: str                          # one of REASONS
    flow_mm3_s: Optional[float] = None   # measured volumetric flow over it
    temp_c: Optional[float] = None       # hotend temperature at end_time
    # the planned (commanded) flow over it, in equal pieces (window_flows)
    commanded_flows: Tuple[float, ...] = ()
    # the sensor's fault when it closed, as the sensor's status names it
    # (None: none). A fault that starts or clears in a batch that closes no
    # window comes in a window of no filament (commanded_mm 0, grip None,
    # reason TOO_LITTLE_MOTION) that carries only this.
    fault: Optional[str] = None

    @property
    def faulted(self) -> bool:
        """Closed while the sensor was faulted: a FAULT window, or the
        window of no filament that brings a fault no window closed in."""
        return self.reason == FAULT or self.fault is not None
