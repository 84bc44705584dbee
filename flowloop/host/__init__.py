"""The printer host: reading printer.cfg, installing into Klipper and Moonraker."""
