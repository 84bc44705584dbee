"""The heater control [measure_profile] swaps in, as PID_CALIBRATE swaps its
own: one PWM held, cut for good when the watchdog says so. It has the shape
of Klipper's heater controls (and Kalico's) but imports neither: the
heater is whatever object calls it.
"""

from __future__ import annotations

from typing import Optional

from ..control import watchdog


class FixedPowerControl:
    """A heater control that holds one PWM (runs in the heater's thread:
    no reactor or G-code calls). On every reading the watchdog's cutoff
    (flowloop.control.watchdog.FixedPowerCutoff: the temperature and host
    rules) says what power to apply.

    Klipper's heater calls temperature_update and check_busy; Kalico's
    calls more of its control (get_profile, get_type, check_valid,
    update_smooth_time, a second sensor's temperature): those answer as
    Kalico's own calibration controls do, and a host that never calls them
    loses nothing."""
    KIND = 'fixed_power'

    def __init__(self, heater, pwm: float, limits: watchdog.WatchdogLimits):
        self.heater = heater
        self.cutoff = watchdog.FixedPowerCutoff(limits, pwm)

    @property
    def stopped(self) -> Optional[str]:
        """Why the power was cut, or None (the reactor reports it)."""
        return self.cutoff.stopped

    def heartbeat(self, print_time: float) -> None:
        """The reactor is alive at print_time."""
        self.cutoff.heartbeat_s = print_time

    def temperature_update(self, read_time, temp, target_temp,
                           secondary_temp=None):
        # (Kalico's dual-sensor heaters pass secondary_temp; not used)
        self.heater.set_pwm(read_time, self.cutoff.power_at(read_time, temp))

    def check_busy(self, eventtime, smoothed_temp, target_temp):
        return False

    # --- what Kalico's heaters ask of a control ------------------------------
    def get_profile(self):
        # Not a PID profile: PID_PROFILE SAVE refuses it, GET lists it
        return {'name': self.KIND, 'control': self.KIND}

    def get_type(self):
        return self.KIND

    def check_valid(self):
        pass     # a fixed power needs no model constants

    def update_smooth_time(self, *args):
        pass     # no smoothing: the power is fixed
