"""Calibrations: CoreXY A/B from printed pylons, delta tower endstops."""
