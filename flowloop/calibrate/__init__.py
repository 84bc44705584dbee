"""Calibrations: CoreXY A/B from printed pylons, delta tower endstops, and the
one parser for the number lists users type into them (numbers.py)."""
