"""G-code: the flow planner (G-code to flow in print time, as Klipper runs it)
and the autotemp annotator that writes the flow ahead into the file."""
