# flowloop component: a job's flowloop figures in Moonraker's job history.
#
# One auxiliary field per figure of flowloop.report.job_figures (provider
# "sensor flowloop"), registered through the history's public API as
# Moonraker's own [sensor] history fields are: a number with its units from
# the job's first moment (each field's reset gives its "unknown" value when a
# job is added), updated while the job runs; the history stores them when
# the job ends. The summed figures are also read as options of a
# [sensor flowloop] section, defaulting to their declaration, so Moonraker's
# parsed configuration (/server/config) holds them as that section would:
# what Mainsail takes a history column's and a total's name and units from
# (job_figures.mainsail_history_fields). No such section is written to
# moonraker.conf (Moonraker's sensor component would refuse its type).
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Dict

from flowloop.report.job_figures import (
    FIGURES,
    PROVIDER,
    Figure,
    JobFigure,
    mainsail_history_fields,
)

# Moonraker's own sensor and spoolman components register their history
# fields with this class too: history.register_auxiliary_field is the API,
# and neither Moonraker 0.11 nor its git checkout has another way in.
from ...common import HistoryFieldData

if TYPE_CHECKING:
    from ...confighelper import ConfigHelper


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
    def __init__(self, config: ConfigHelper) -> None:
        self.fields: Dict[str, HistoryFieldData] = {
            figure.name: _field(figure) for figure in FIGURES}
        section = config.getsection(PROVIDER)
        for option, declaration in mainsail_history_fields().items():
            section.getdict(option, declaration)
        history = config.get_server().lookup_component("history", None)
        if history is not None:
            for field in self.fields.values():
                history.register_auxiliary_field(field)

    def update(self, figures: Dict[str, Figure]) -> None:
        """The running job's figures (the history keeps them only while a
        job runs)."""
        for name, value in figures.items():
            self.fields[name].tracker.update(value)
