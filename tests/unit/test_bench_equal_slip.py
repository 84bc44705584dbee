"""The limiter bench's comparison at equal under-extrusion: predictive's
print time against the limiter that knows the capacity, told the share of
it at which it would under-extrude as much (tests/bench)."""

from __future__ import annotations

import math

import pytest

from tests.bench.bench_flowrate_limiter import KNOWING, KNOWING_SHARES, equal_slip_time


def _knowing(low, at, high):
    """(lost mm, time s) told 99 %, 100 % and 101 % of the capacity."""
    return {KNOWING[KNOWING_SHARES[0]]: low, "knowing the capacity": at,
            KNOWING[KNOWING_SHARES[-1]]: high}


def test_between_the_shares_it_reads_the_time_at_that_slip():
    r = _knowing((0.0, 381.0), (0.8, 379.0), (2.6, 377.0))
    assert equal_slip_time(r, 0.8) == pytest.approx(379.0)
    assert equal_slip_time(r, 0.4) == pytest.approx(380.0)
    assert equal_slip_time(r, 1.7) == pytest.approx(378.0)


def test_outside_them_it_holds_the_end_share():
    r = _knowing((0.0, 381.0), (0.8, 379.0), (2.6, 377.0))
    assert equal_slip_time(r, -0.01) == pytest.approx(381.0)
    assert equal_slip_time(r, 5.0) == pytest.approx(377.0)


def test_a_slip_that_does_not_rise_with_the_share_reads_nothing():
    r = _knowing((0.5, 381.0), (0.5, 379.0), (2.6, 377.0))
    assert math.isnan(equal_slip_time(r, 0.5))
