# flowloop component: a job's flowloop figures in Moonraker's job history.
#
# One auxiliary field per figure of flowloop.report.job_figures (provider
# flowloop), registered through the history's public API as Moonraker's own
# [sensor] history fields are: a number with its units from the job's first
# moment (each field's reset gives its "unknown" value when a job is added),
# updated while the job runs; the history stores them when the job ends.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Dict

from flowloop.report.job_figures import FIGURES, Figure, JobFigure

# Moonraker's own sensor and spoolman components register their history
# fields with this class too: history.register_auxiliary_field is the API,
# and neither Moonraker 0.11 nor its git checkout has another way in.
from ...common import HistoryFieldData

if TYPE_CHECKING:
    from ...server import Server

PROVIDER = "flowloop"


def _field(figure: JobFigure) -> HistoryFieldData:
    field = HistoryFieldData(
        figure.name, PROVIDER, figure.description, "basic", units=figure.units,
        reset_callback=lambda: copy.copy(figure.unknown),
        report_total=figure.report_total, report_maximum=figure.report_maximum,
        precision=figure.precision)
    # a number before the first job too: the history's totals count a field
    # only while it holds one
    field.tracker.reset()
    return field


class JobHistory:
    def __init__(self, server: Server) -> None:
        self.fields: Dict[str, HistoryFieldData] = {
            figure.name: _field(figure) for figure in FIGURES}
        history = server.lookup_component("history", None)
        if history is not None:
            for field in self.fields.values():
                history.register_auxiliary_field(field)

    def update(self, figures: Dict[str, Figure]) -> None:
        """The running job's figures (the history keeps them only while a
        job runs)."""
        for name, value in figures.items():
            self.fields[name].tracker.update(value)
