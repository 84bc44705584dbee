"""The watchdog of a heater held at a fixed power (profile measurement).

A heater at fixed power has no controller watching its temperature: these
rules do. Each is a pure function that returns why the level must end (one
line) or None; `stop_reason` asks them all. The klippy adapter runs them on
every temperature reading (the heater's own thread: it then only cuts the
power) and on every step of the measurement (the reactor: it then restores
the heater's control and says why).

- the temperature is above the limit (the lower of the profile's and the
  heater's max_temp), or below the profile's minimum (the extruder never
  pushes filament through a hotend colder than that),
- the temperature does not move as a held heater's should: at fixed power
  it settles or sags as the flow rises; rising well above where it settled
  (heater output stuck, thermistor off its block) or falling faster than
  any hotend cools (thermistor fault) ends the level,
- the flow sensor reports a fault (no grip can be judged),
- the host stopped answering (no heartbeat within host_timeout_s).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

from ..errors import FlowloopError
from ..material.profile import Bounds

DEFAULT_MAX_RISE_C = 10.0
DEFAULT_MAX_FALL_C_PER_S = 5.0
DEFAULT_HOST_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class WatchdogLimits:
    min_temp_c: float
    max_temp_c: float
    max_rise_c: float = DEFAULT_MAX_RISE_C
    max_fall_c_per_s: float = DEFAULT_MAX_FALL_C_PER_S
    host_timeout_s: float = DEFAULT_HOST_TIMEOUT_S

    def __post_init__(self):
        for name in ("min_temp_c", "max_temp_c", "max_rise_c",
                     "max_fall_c_per_s", "host_timeout_s"):
            if not math.isfinite(getattr(self, name)):
                raise FlowloopError(f"{name} must be a finite number")
        if not self.min_temp_c < self.max_temp_c:
            raise FlowloopError(f"the minimum temperature {self.min_temp_c:g} degC"
                                f" must be below the maximum {self.max_temp_c:g}"
                                f" degC")
        for name in ("max_rise_c", "max_fall_c_per_s", "host_timeout_s"):
            if not getattr(self, name) > 0:
                raise FlowloopError(f"{name} must be above 0")


def temperature_stop(limits: WatchdogLimits, temp_c: float) -> Optional[str]:
    """Outside min..max (a reading that is not a number counts as outside)."""
    if not math.isfinite(temp_c):
        return f"the temperature reading {temp_c} is not a number"
    if temp_c > limits.max_temp_c:
        return (f"temperature {temp_c:.1f} degC is above the limit "
                f"{limits.max_temp_c:g} degC")
    if temp_c < limits.min_temp_c:
        return (f"temperature {temp_c:.1f} degC is below the profile's minimum "
                f"{limits.min_temp_c:g} degC")
    return None


def trend_stop(limits: WatchdogLimits, settled_c: float,
               previous: Tuple[float, float], now: Tuple[float, float]
               ) -> Optional[str]:
    """At fixed power from `settled_c`: (time_s, temp_c) readings, previous
    and now. Rising past settled + max_rise_c, or falling faster than
    max_fall_c_per_s, is not what a held heater does."""
    (t0, temp0), (t1, temp1) = previous, now
    if temp1 > settled_c + limits.max_rise_c:
        return (f"temperature rose to {temp1:.1f} degC at fixed power, more than"
                f" {limits.max_rise_c:g} degC above where it settled "
                f"({settled_c:.1f} degC): heater or thermistor fault?")
    dt = t1 - t0
    if dt > 0 and (temp0 - temp1) / dt > limits.max_fall_c_per_s:
        return (f"temperature fell {(temp0 - temp1) / dt:.1f} degC/s at fixed "
                f"power (limit {limits.max_fall_c_per_s:g}): thermistor fault?")
    return None


def sensor_stop(fault: Optional[str]) -> Optional[str]:
    if fault:
        return f"flow sensor fault '{fault}': grip cannot be judged"
    return None


def host_stop(limits: WatchdogLimits, now_s: float,
              heartbeat_s: Optional[float]) -> Optional[str]:
    """No heartbeat from the host (the measurement's reactor) for too long."""
    if heartbeat_s is not None and now_s - heartbeat_s > limits.host_timeout_s:
        return (f"the host has not answered for {now_s - heartbeat_s:.1f} s "
                f"(limit {limits.host_timeout_s:g} s)")
    return None


def stop_reason(limits: WatchdogLimits, *, temp_c: float, now_s: float,
                settled_c: Optional[float] = None,
                previous: Optional[Tuple[float, float]] = None,
                sensor_fault: Optional[str] = None,
                heartbeat_s: Optional[float] = None) -> Optional[str]:
    """Why a fixed-power level must end now, or None: the first rule that
    says so (temperature, trend, sensor, host)."""
    reason = temperature_stop(limits, temp_c)
    if reason is None and settled_c is not None and previous is not None:
        reason = trend_stop(limits, settled_c, previous, (now_s, temp_c))
    return (reason or sensor_stop(sensor_fault)
            or host_stop(limits, now_s, heartbeat_s))


def for_measurement(bounds: Bounds,
                    host_timeout_s: float = DEFAULT_HOST_TIMEOUT_S
                    ) -> Tuple[WatchdogLimits, Callable[..., Optional[str]]]:
    """A profile measurement's watchdog: its limits (the bounds' min..max;
    the fixed-power heater's cutoff applies them) and its rules with them
    (stop_reason, what the procedure asks on every reading)."""
    limits = WatchdogLimits(min_temp_c=bounds.min_temp_c,
                            max_temp_c=bounds.max_temp_c,
                            host_timeout_s=host_timeout_s)
    return limits, functools.partial(stop_reason, limits)


class FixedPowerCutoff:
    """The rules a fixed-power heater control applies on every reading, in
    the heater's own thread (no reactor needed): the power asked for until
    the temperature or the host rule says stop, then 0 for good (`stopped`
    says why; the reactor reports it). The host sets `heartbeat_s` (print
    time) as it runs; None: no host rule yet."""

    def __init__(self, limits: WatchdogLimits, power: float):
        self.limits = limits
        self.power = power
        self.heartbeat_s: Optional[float] = None
        self.stopped: Optional[str] = None

    def power_at(self, read_time_s: float, temp_c: float) -> float:
        if self.stopped is None:
            self.stopped = (temperature_stop(self.limits, temp_c)
                            or host_stop(self.limits, read_time_s,
                                         self.heartbeat_s))
        return 0.0 if self.stopped else self.power
