"""A job's flowloop figures as Moonraker's history keeps them: a finite
number with units for every field from the job's first moment, or the empty
list both UIs show as "--" where nothing was judged and no total needs a
number (never a string or null)."""

from __future__ import annotations

import math

import pytest

from flowloop.report import job_figures
from flowloop.report.recorder import Job, Recorder, Sample

pytestmark = pytest.mark.unit


def names():
    return {f.name for f in job_figures.FIGURES}


def shown(value):
    """What both UIs can render: a finite number or an empty list."""
    return value == [] or (isinstance(value, float) and math.isfinite(value))


def test_every_field_has_units_and_a_renderable_unknown():
    assert {"under_extruded", "lowest_grip", "limiter_slowed", "peak_flow",
            "melt_ratio"} <= names()
    for figure in job_figures.FIGURES:
        assert figure.units and shown(figure.unknown), figure


def test_a_job_just_started_has_no_grip_judged_yet():
    # was 100 %: a grip no sensor ever measured
    figures = job_figures.recorded(Recorder())
    assert figures == {"under_extruded": 0.0, "lowest_grip": [],
                       "limiter_slowed": 0.0, "peak_flow": 0.0}


def test_a_field_in_the_totals_is_always_a_number():
    # Moonraker rebuilds its totals from the fields holding a number: a list
    # in one job would drop the field's running total
    for figure in job_figures.FIGURES:
        if figure.report_total or figure.report_maximum:
            assert isinstance(figure.unknown, float), figure


def test_a_job_without_a_working_sensor_judges_no_flow():
    rec = Recorder(job=Job(filename="a.gcode"))
    for i in range(8):
        rec.sample(Sample(i / 4, commanded_flow_mm3_s=12.0, slowed_time_s=0.5 * i,
                          cap_reason="max_flow", layer=1, sensor=False))
    figures = job_figures.recorded(rec)
    assert figures["lowest_grip"] == []
    assert figures["under_extruded"] == figures["peak_flow"] == 0.0
    assert figures["limiter_slowed"] == 3.5


def test_the_figures_follow_the_recording():
    rec = Recorder(job=Job(filename="a.gcode"))
    for i in range(40):
        rec.sample(Sample(i / 4, commanded_flow_mm3_s=12.0,
                          measured_flow_mm3_s=-2.0 if i == 5 else 10.2,
                          grip=0.85, slowed_time_s=0.1 * i, cap_reason="grip",
                          layer=1))
    figures = job_figures.recorded(rec)
    assert figures["lowest_grip"] == 85.0
    assert figures["peak_flow"] == 10.2
    assert figures["limiter_slowed"] == 3.9
    assert figures["under_extruded"] == round(rec.under_mm, 2) > 0


def test_the_melt_ratio_is_the_newest_judged_in_percent():
    assert job_figures.melt_ratio(0.912) == 91.2
    assert job_figures.melt_ratio(float("nan")) == []
    assert job_figures.melt_ratio(None) == []


def test_no_figure_has_a_maximum_mainsail_would_show_as_a_total():
    # Mainsail shows a total's sum only: the peak flow's maximum read
    # "peak_flow 0 undefined" in its statistics (a sum of peaks means nothing)
    assert not any(f.report_maximum for f in job_figures.FIGURES)


def test_mainsail_is_given_the_summed_figures_names_and_units():
    # as a [sensor flowloop] section's history_field_* options: Mainsail's
    # columns and statistics take their name and units from there, matched by
    # provider (they read "under_extruded 0 undefined")
    assert job_figures.PROVIDER == "sensor flowloop"
    assert job_figures.mainsail_history_fields() == {
        "history_field_under_extruded": {"desc": "Filament under-extruded",
                                         "units": "mm", "parameter": "under_extruded"},
        "history_field_limiter_slowed": {"desc": "Limiter slowed the print",
                                         "units": "s", "parameter": "limiter_slowed"},
    }
    # only what a sum over the selected jobs means something for
    summed = {f.name for f in job_figures.FIGURES if f.report_total}
    assert {k[len("history_field_"):] for k in
            job_figures.mainsail_history_fields()} == summed
