"""The filament sensor: EMS22 frames and decoding, grip windows, the pipeline
that joins them, and the simulated twin. Its calibrations (scale, the
extruder's rotation_distance) are in flowloop.calibrate.flow_sensor."""
