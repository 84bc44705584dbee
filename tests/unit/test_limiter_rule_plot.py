"""The reactive rule's plot in the docs is the rule's own output, and the
scenario it shows says what the rule is for."""

from __future__ import annotations

from pathlib import Path

from flowloop.control import rule_plot

SVG = Path(__file__).resolve().parents[2] / "docs" / "flowrate_limiter_rule.svg"


def test_the_docs_plot_is_what_the_rule_does_now():
    # regenerate: python -c "from flowloop.control import rule_plot as r;
    #   open('docs/flowrate_limiter_rule.svg', 'w').write(r.svg())"
    assert SVG.read_text() == rule_plot.svg()


def test_flowloop_s_rule_loses_less_and_slips_less_often_than_ddprint_s():
    ours, theirs = rule_plot.simulate("flowloop"), rule_plot.simulate("ddprint")
    assert rule_plot.under_extrusion(ours) < 0.5 * rule_plot.under_extrusion(theirs)

    def slips(run):
        return sum(1 for a, b in zip(run, run[1:]) if a[2] >= 0.9 > b[2])

    assert slips(ours) < slips(theirs)
    # and it never raises a speed above what the G-code asked for
    assert max(f for _, f, _ in ours) == 1.0
