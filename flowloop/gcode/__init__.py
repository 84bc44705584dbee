"""G-code: the flow planner (G-code to flow in print time, as Klipper runs it:
bulk_planner.py, which flowloop runs, and reference_planner.py, the line-by-line
reference it must match) and the autotemp annotator that writes the flow ahead
into the file."""
