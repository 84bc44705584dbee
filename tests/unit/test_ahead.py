"""flowloop.gcode.ahead: an iterator run ahead in a thread gives the same
items in order, raises what it raised where it raised it, stays at most
depth ahead and stops when its consumer does."""

from __future__ import annotations

import threading
import time

import pytest

from flowloop.errors import FlowloopError
from flowloop.gcode.ahead import ahead


def threads_ahead():
    return [t for t in threading.enumerate() if t.name == "flowloop-ahead"]


def wait_until_gone(timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while threads_ahead():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


@pytest.mark.parametrize("depth", [1, 2, 4])
def test_the_items_in_order(depth):
    assert list(ahead(iter(range(1000)), depth)) == list(range(1000))
    assert wait_until_gone()


def test_what_the_iterator_raises_comes_after_the_items_before_it():
    def items():
        yield 1
        yield 2
        raise FlowloopError("line 3: bad word")
    got = []
    with pytest.raises(FlowloopError, match="line 3: bad word"):
        for item in ahead(items()):
            got.append(item)
    assert got == [1, 2]
    assert wait_until_gone()


def test_it_stays_at_most_depth_ahead():
    made = []

    def items():
        for k in range(100):
            made.append(k)
            yield k
    it = ahead(items(), depth=3)
    assert next(it) == 0
    time.sleep(0.3)
    # three waiting, one the thread holds until there is room, one taken
    assert len(made) <= 5
    it.close()
    assert wait_until_gone()
    assert len(made) <= 6


def test_a_consumer_that_stops_stops_the_thread():
    def endless():
        k = 0
        while True:
            yield k
            k += 1
    with pytest.raises(RuntimeError, match="the consumer's own"):
        for item in ahead(endless(), depth=2):
            if item == 10:
                raise RuntimeError("the consumer's own")
    assert wait_until_gone()
