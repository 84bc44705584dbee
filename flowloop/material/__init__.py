"""Material profiles: the schema and its lines, ddPrint's format, plots.

The one melt line everything uses (autotemp, the limiters, the plots, the
simulated twin) is `profile_line(profile, working_point)`, a `Line` with
`flow_mm3_s(temp_c)` and `temp_c(flow_mm3_s)`; `Line.through(slope, temp_c,
flow_mm3_s)` builds one from a point.
"""

from .profile import Line, profile_line

__all__ = ["Line", "profile_line"]
