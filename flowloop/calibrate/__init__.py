"""Calibrations: a printer's own numbers found from what it measured or
printed. CoreXY A/B from printed pylons (diff_ab, pylons), delta tower
endstops (delta), and the flow sensor's scale and the extruder's
rotation_distance from slow extrusions (flow_sensor).

Where a new fit goes: a number of the printer (a distance, a scale, an
endstop) is a calibration, here; what a material melts at a temperature is a
profile, in flowloop.material (measure, fit); grip windows and sensor
decoding, which every calibration and profile reads, are flowloop.sensor."""
