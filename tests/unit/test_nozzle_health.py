"""Nozzle health from grip (flowloop.control.nozzle_health): a print's melt
capacity against its profile with the error its own sensor noise allows,
and the verdict over prints, on the simulated twin and hotend model."""

from __future__ import annotations

import copy
import dataclasses
import functools

import numpy as np
import pytest

from flowloop.control import nozzle_health as nh
from flowloop.window import FAULT, Window
from tests.nozzle_prints import MIN_GRIP, PROFILE, simulate_print

pytestmark = pytest.mark.unit

# 2 % of the capacity lost per print: the print's highest flows (the
# profile's capacity) slip below min_grip once the ratio is under 0.9
DEGRADE_PER_PRINT = 0.02


def estimate_of(windows, profile=PROFILE):
    return nh.estimate(nh.evidence_of(windows, profile))


def degrading_prints(seed=0, prints=10):
    """(true ratio, estimate, verdict after it) print by print."""
    history, out = [], []
    for k in range(prints):
        ratio = 1.0 - DEGRADE_PER_PRINT * k
        e = estimate_of(simulate_print(ratio, seed=seed + k))
        history.append(e)
        out.append((ratio, e, nh.judge(history)))
    return out


@pytest.mark.parametrize("seed", [0, 100])
def test_a_degrading_hotend_warns_before_grip_falls_below_min_grip(seed):
    prints = degrading_prints(seed)
    warned = [ratio for ratio, _, verdict in prints if verdict.warn]
    assert warned, [(r, e.ratio, v.text) for r, e, v in prints]
    # grip at the print's highest flow (the profile's capacity) is the ratio
    assert warned[0] > MIN_GRIP
    first = next(e for _, e, v in prints if v.warn)
    assert first.limit_ratio == pytest.approx(MIN_GRIP * first.at_least)


def test_each_estimate_finds_the_twins_ratio_within_its_error():
    for ratio in (0.95, 0.9, 0.8):
        e = estimate_of(simulate_print(ratio, seed=3))
        assert e.reason == ""
        # the window model against the twin's smoothed melt: < 1 % high
        assert ratio - 3 * e.standard_error < e.ratio < ratio + 0.01


@pytest.mark.parametrize("seed", range(5))
def test_a_healthy_noisy_hotend_never_warns(seed):
    history = []
    for k in range(12):
        history.append(estimate_of(simulate_print(1.0, seed=1000 * seed + k)))
        assert not nh.judge(history).warn, history[-1]


def test_a_healthy_hotend_printing_slowly_is_at_least_what_it_was_asked():
    # a sensor that reads 1 % low would otherwise look like a slip at the top
    windows = [dataclasses.replace(w, grip=w.grip * 0.99)
               if w.grip is not None else w
               for w in simulate_print(1.0, seed=4)]
    e = estimate_of(windows)
    assert e.ratio is None and "kept up" in e.reason


def test_one_very_noisy_print_never_warns_alone():
    noisy = estimate_of(simulate_print(0.9, seed=5, noise_counts=6.0))
    quiet = [estimate_of(simulate_print(1.0, seed=6 + k)) for k in range(5)]
    assert not nh.judge(quiet + [noisy]).warn
    assert not nh.judge([noisy]).warn
    # its error is its own noise's: twenty times the quiet prints'
    assert noisy.grip_noise > 20 * max(e.grip_noise for e in quiet)
    assert noisy.reason or noisy.standard_error > 20 * max(
        e.standard_error or 0.0 for e in quiet)


def test_a_print_without_windows_has_no_estimate():
    e = estimate_of([])
    assert e.ratio is None and e.reason == \
        "no judged grip window at a known temperature"


def test_a_print_without_a_profile_has_no_estimate():
    e = estimate_of(simulate_print(0.9, layers=1), profile=None)
    assert e.ratio is None and "no active profile" in e.reason


def test_a_sensor_faulted_the_whole_print_has_no_estimate():
    windows = [dataclasses.replace(w, grip=None, reason=FAULT, fault="magnet")
               for w in simulate_print(0.9, layers=1)]
    e = estimate_of(windows)
    assert e.ratio is None
    assert e.reason.startswith(f"the sensor was faulted for all {len(windows)}")


def test_a_print_too_short_to_measure_the_noise_says_so():
    e = estimate_of(simulate_print(0.9, layers=1)[:10])
    assert e.ratio is None and "needed to measure the sensor's noise" in e.reason


def test_windows_without_temperature_are_counted_not_judged():
    w = Window(0.0, 1.0, 2.0, 2.0, 1.0, "judged", temp_c=None)
    ev = nh.evidence_of([w], PROFILE)
    assert ev.no_temperature == 1 and ev.windows == 0


def test_evidence_between_two_snapshots_is_the_print_between():
    first = simulate_print(0.9, seed=7, layers=3)
    second = simulate_print(0.8, seed=8, layers=3)
    start = nh.evidence_of(first, PROFILE)
    end = nh.PrintEvidence.from_dict(start.to_dict())
    line = nh.profile_line(PROFILE)
    for w in second:
        end.add(w, line)
    between = nh.evidence_between(start, end)
    alone = nh.evidence_of(second, PROFILE)
    assert between.windows == alone.windows
    assert nh.estimate(between).ratio == pytest.approx(nh.estimate(alone).ratio)
    # a sum begun after the start (a profile activated at print start) is whole
    assert nh.evidence_between(start, alone) is alone
    assert nh.evidence_between(None, alone) is alone
    assert nh.evidence_between(start, None) is None


def test_evidence_that_is_not_evidence_is_refused_in_one_line():
    with pytest.raises(nh.FlowloopError, match="not nozzle evidence"):
        nh.PrintEvidence.from_dict({"version": 1})
    with pytest.raises(nh.FlowloopError, match="version"):
        nh.PrintEvidence.from_dict({"version": 99})


def test_prints_without_an_estimate_neither_warn_nor_count():
    none = nh.PrintEstimate("known", reason="no judged grip window")
    verdict = nh.judge([none] * 10)
    assert not verdict.warn and verdict.prints == 0


def worked_example_rows():
    """docs/nozzle_health.md's table: the degrading hotend, seed 0."""
    rows = []
    for k, (ratio, e, verdict) in enumerate(degrading_prints(0, prints=6)):
        found = "none: all kept up" if e.ratio is None else \
            f"{e.ratio:.3f} ± {e.standard_error:.4f}"
        rows.append(f"| {k + 1} | {ratio:.2f} | {e.grip_noise:.4f} | {found} | "
                    f"{'**warn** (' + verdict.rule + ')' if verdict.warn else 'no'} |")
    return rows


def test_the_docs_worked_example_is_what_the_twin_gives():
    from pathlib import Path
    doc = (Path(__file__).resolve().parents[2] / "docs"
           / "nozzle_health.md").read_text()
    for row in worked_example_rows():
        assert row in doc, row


def test_the_limiter_sums_the_evidence_of_the_active_profile():
    from flowloop.control.limiter import FlowLimiter
    limiter = FlowLimiter()
    windows = simulate_print(0.9, seed=9, layers=2)
    for w in windows:
        limiter.on_window(w)
    assert limiter.evidence is None        # no profile: nothing to compare
    limiter.set_profile(PROFILE)
    for w in windows:
        limiter.on_window(w)
    assert limiter.evidence.to_dict() == nh.evidence_of(
        windows, PROFILE).to_dict() | {"epoch": limiter.evidence.epoch}


def test_the_docs_picture_is_the_worked_example():
    """docs/nozzle_health.svg is what health_plot draws for the worked
    example; FLOWLOOP_WRITE_DOCS=1 writes it after a deliberate change."""
    import os
    from pathlib import Path

    from flowloop.control.health_plot import svg
    path = Path(__file__).resolve().parents[2] / "docs" / "nozzle_health.svg"
    drawn = svg([e for _, e, _ in degrading_prints(0, prints=6)],
                "hotend v6-0.4, profile known")
    if os.environ.get("FLOWLOOP_WRITE_DOCS"):
        path.write_text(drawn)
    assert path.read_text() == drawn


def test_a_toolchanger_judges_each_tool_that_printed_as_its_own_hotend():
    assert nh.tool_hotend("v6", "extruder") == "v6"
    assert nh.tool_hotend("v6", "extruder1") == "v6 extruder1"
    before = {"windows": 40, "epoch": 1}
    assert not nh.printed_between(before, {"windows": 40, "epoch": 1})  # idle
    assert nh.printed_between(before, {"windows": 41, "epoch": 1})
    # its profile changed (a new epoch): a new sum, judged
    assert nh.printed_between(before, {"windows": 40, "epoch": 2})
    assert nh.printed_between(None, {"windows": 3, "epoch": 1})
    assert not nh.printed_between(before, None)    # no profile now


def _falling(ratios, at_least):
    return [nh.PrintEstimate("known", ratio=r, standard_error=0.002,
                             grip_noise=0.005, at_least=at_least, windows=40,
                             min_grip=0.9) for r in ratios]


def test_a_fall_that_soon_reaches_min_grip_warns_by_its_trend():
    # only the latest print is below 97 %: not persistent, but the line
    # through the last prints reaches the ratio where the prints' highest
    # flows (105 % of the capacity) read grip below min_grip within 5 prints
    ratios = [1.00, 0.99, 0.98, 0.975, 0.96]
    verdict = nh.judge(_falling(ratios, at_least=1.05))
    assert (verdict.warn, verdict.rule) == (True, "trend"), verdict
    assert "a print" in verdict.text
    # the same fall, prints that ask little (limit 0.81): far off, no warning
    assert not nh.judge(_falling(ratios, at_least=0.9)).warn
    # and no fall: the latest low alone is not a trend
    assert not nh.judge(_falling([0.99, 1.0, 0.99, 1.0, 0.96], at_least=1.05)).warn


# --- what comes from outside ---------------------------------------------------

@functools.cache
def _evidence_of(seed, ratio):
    return nh.evidence_of(simulate_print(ratio, seed=seed), PROFILE).to_dict()


def _evidence(seed=0, ratio=0.9):
    """A print's evidence as klippy gives it (a fresh copy each call)."""
    return copy.deepcopy(_evidence_of(seed, ratio))


@pytest.mark.parametrize("name, value, says", [
    ("min_grip", "nan", "min_grip must be a number"),
    ("min_grip", float("nan"), "min_grip must be a number"),
    ("min_grip", None, "min_grip must be a number"),
    ("noise_sum", 1e308, "noise_sum must be a number within"),
    ("noise_sum", float("inf"), "noise_sum must be a number within"),
    ("noise_sum_sq", -1, "noise_sum_sq is a sum of squares"),
    ("windows", "3", "windows must be a whole number"),
    ("windows", True, "windows must be a whole number"),
    ("windows", -1, "windows must be a whole number"),
    ("windows", 2.5, "windows must be a whole number"),
    ("profile", "a\n!! MCU 'mcu' shutdown", "control character"),
    ("profile", "x" * 10_000_000, "longer than 128"),
    ("profile", 12, "must be a string"),
    ("epoch", "e" * 1000, "epoch"),
    ("working_point", float("inf"), "working point"),
    ("version", True, "version true is not 1"),
    ("cross", [0.0] * 3, "cross must be a list of 121"),
    ("information", [-1.0] * 121, "information is a sum of squares"),
    ("model_sq", [float("nan")] * 121, "model_sq must be a number"),
])
def test_evidence_no_print_gives_is_refused_whole_in_one_line(name, value, says):
    data = {**_evidence(), name: value}
    with pytest.raises(nh.FlowloopError, match="not nozzle evidence") as e:
        nh.PrintEvidence.from_dict(data)
    assert says in str(e.value) and "\n" not in str(e.value)
    assert len(str(e.value)) < 300


def test_extreme_but_finite_sums_give_a_reason_not_an_overflow():
    data = _evidence()
    for sums in ({"noise_sum": -data["noise_windows"]},      # grip 0 where easy
                 {"noise_sum_sq": nh.MAX_SUM, "grip_sq": nh.MAX_SUM},
                 {"information": [nh.MAX_SUM] * 121,
                  "cross": [-nh.MAX_SUM] * 121}):
        found = nh.estimate(nh.PrintEvidence.from_dict({**data, **sums}))
        assert all(v is None or np.isfinite(v) for v in
                   (found.ratio, found.standard_error, found.grip_noise)), sums
        assert found.to_dict()   # JSON-able, no OverflowError


@pytest.mark.parametrize("job_id, says", [
    ("00ﬀ00", "not a job of Moonraker"),      # U+FB00 upper-cases to FF
    ("0000FF\n", "not a job of Moonraker"),
    ("FF", "not a job of Moonraker"),
    ("1" * 17, "not a job of Moonraker"),
    (12, "job id int is not"),
    (None, "job id NoneType is not"),
    (["000001"], "job id list is not"),
])
def test_a_posted_job_id_is_one_of_moonrakers(job_id, says):
    with pytest.raises(nh.FlowloopError, match=says):
        nh.post_request({"job_id": job_id}, {"known"})


def test_a_posted_print_is_checked_whole_against_the_stored_profiles():
    posted = nh.post_request({"job_id": "00002a", "evidence": _evidence()},
                             {"known"})
    assert posted.job_id == "00002A" and posted.end.profile == "known"
    with pytest.raises(nh.FlowloopError, match='no profile named "known"'):
        nh.post_request({"job_id": "00002A", "evidence": _evidence()}, {"other"})
    start = _evidence()
    end = {**start, "windows": start["windows"] - 1}
    with pytest.raises(nh.FlowloopError, match="the start counts more windows"):
        nh.post_request({"job_id": "00002A", "start": start, "evidence": end},
                        {"known"})
    with pytest.raises(nh.FlowloopError, match="a start without evidence"):
        nh.post_request({"job_id": "00002A", "start": start}, {"known"})


def test_a_job_is_one_record_and_a_history_is_capped():
    prints = []
    for k in range(3):
        prints = nh.with_print(prints, {"job_id": "000001", "ratio": 0.9 + k / 100})
    assert prints == [{"job_id": "000001", "ratio": 0.92}]
    for k in range(nh.MAX_PRINTS_KEPT + 5):
        prints = nh.with_print(prints, {"job_id": f"{k + 2:06X}"})
    assert len(prints) == nh.MAX_PRINTS_KEPT
    assert prints[-1]["job_id"] == f"{nh.MAX_PRINTS_KEPT + 6:06X}"


def test_a_stored_print_that_does_not_read_is_skipped_not_blocking():
    good = nh.PrintEstimate("known", ratio=0.9, standard_error=0.01).to_dict()
    bad = {**good, "min_grip": None}            # what a NaN was stored as
    prints, estimates, problems = nh.load_history(
        {"prints": [good, bad, {**good, "ratio": "x"}, 7, good]})
    assert prints == [good, good] and len(estimates) == 2
    assert [p.split(":")[0] for p in problems] == ["print 1", "print 2", "print 3"]
    assert nh.load_history({"prints": None})[2]


def test_a_name_is_shown_on_one_line_without_markup():
    shown = nh.label("PLA\n!! MCU 'mcu' shutdown <img src=x onerror=alert(1)> & é")
    assert "\n" not in shown and not set("<>&'") & set(shown)
    assert shown.isascii() and shown.startswith('"PLA\\n!! MCU')


def test_the_warning_reads_without_stray_punctuation_and_links_its_plot():
    verdict = nh.Verdict(True, "persistent", "melt capacity 90% of the profile; "
                         "a partial clog, a worn nozzle or the wrong nozzle?", 5)
    prints = [{"ratio": 0.92}, {"ratio": None}, {"ratio": 0.9}]
    text = nh.warning_text(verdict, prints)
    assert "?." not in text and ".." not in text
    assert text.endswith("wrong nozzle? Melt capacity against the profile over "
                         "the last prints: 92%, 90%.")
    assert nh.warning_text(nh.Verdict(True, "trend", "falling", 5), []) == "falling."
    assert nh.plot_path("v6 0.4", "PLA & co") == (
        "/server/flowloop/nozzle_health/plot?profile=PLA+%26+co&hotend=v6+0.4")


WARNS = nh.Verdict(True, "persistent", "melt capacity 90% of the profile", 5)
CALM = nh.Verdict(False, "", "melt capacity 99% of the profile", 5)


def test_a_warning_is_announced_when_it_starts_not_while_it_goes_on():
    prints = [{"ratio": 0.9}]
    started = nh.health_warning("v6", "PLA", prints, WARNS, warned_before=False)
    going_on = nh.health_warning("v6", "PLA", prints, WARNS, warned_before=True)
    assert started.announce and not going_on.announce
    # both still said: the console line and the notification every print
    assert started.text == going_on.text == nh.warning_text(WARNS, prints)
    assert nh.health_warning("v6", "PLA", prints, CALM, warned_before=True) is None


def test_a_warning_comes_back_announced_after_a_calm_verdict():
    calm = nh.history_record("v6", "PLA", [], CALM)
    warned = nh.history_record("v6", "PLA", [], WARNS)
    assert not nh.was_warning(None) and not nh.was_warning(calm)
    assert nh.was_warning(warned)
    assert not nh.was_warning({"verdict": {"warn": "yes"}})
    again = nh.health_warning("v6", "PLA", [], WARNS, nh.was_warning(calm))
    assert again.announce


def test_a_warning_names_its_hotend_and_profile_without_markup_and_links_its_plot():
    warning = nh.health_warning("v6 0.4", "PLA <b>", [], WARNS, False)
    assert warning.title == ('flowloop: nozzle health, hotend "v6 0.4", profile '
                             '"PLA \\u003cb\\u003e"')
    assert warning.url == nh.plot_path("v6 0.4", "PLA <b>")


def test_a_history_is_stored_only_when_it_reads_whole():
    good = nh.PrintEstimate("PLA", ratio=0.9, standard_error=0.01).to_dict()
    record = nh.history_record("v6", "PLA", [{"job_id": "000001", **good}], WARNS)
    assert nh.check_history(record) == record
    for bad, says in [
            ({**record, "prints": [{**good, "ratio": "x"}]}, "print 0"),
            ({**record, "prints": [{**good, "profile": "PETG"}]}, "another profile"),
            ({**record, "hotend": ""}, "hotend"),
            ({**record, "profile": " pad"}, "whitespace"),
            ({**record, "verdict": {"warn": None}}, "verdict"),
            ({**record, "prints": [good] * (nh.MAX_PRINTS_KEPT + 1)}, "at most"),
            ({**record, "extra": 1}, "not a nozzle health history"),
            ([], "not a nozzle health history")]:
        with pytest.raises(nh.FlowloopError, match=says):
            nh.check_history(bad)
