"""The filament sensor: EMS22 frames and decoding, grip, and the simulated twin."""
