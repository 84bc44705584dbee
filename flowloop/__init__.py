"""flowloop core: closed-loop extrusion and calibration math for Klipper.

Pure Python: nothing here imports Klipper or Moonraker. Adapters in
klippy_extras/ and moonraker_components/ read config and talk to the hosts;
the numbers are decided here.
"""

__version__ = "0.1.0"
