"""flowloop.gcode.ahead: an iterator run ahead in a thread or a child
process gives the same items in order, raises what it raised where it
raised it, stays at most depth ahead and stops when its consumer does."""

from __future__ import annotations

import contextlib
import os
import pickle
import threading
import time

import pytest

from flowloop.errors import FlowloopError
from flowloop.gcode.ahead import DEPTH, ahead, ahead_forked, can_fork, read_exactly


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


@pytest.mark.parametrize("where", ["thread", "child"])
def test_what_the_iterator_raises_comes_after_the_items_before_it(where):
    def items():
        yield 1
        yield 2
        raise FlowloopError("line 3: bad word")
    got = []
    run = ahead(items()) if where == "thread" else forked(items)
    with pytest.raises(FlowloopError, match="line 3: bad word"):
        for item in run:
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


# --- in a child process (ahead_forked) ------------------------------------------

def write_pickled(item, pipe):
    data = pickle.dumps(item)
    pipe.write(len(data).to_bytes(8, "little"))
    pipe.write(data)


def read_pickled(pipe):
    size = int.from_bytes(read_exactly(pipe, 8), "little")
    return pickle.loads(read_exactly(pipe, size))


def forked(make_items, depth=DEPTH):
    return ahead_forked(make_items, write_pickled, read_pickled, depth)


def gone(pid: int, timeout_s: float = 5.0) -> bool:
    """The child has ended and been waited for (no zombie left)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            return True
        time.sleep(0.01)
    return False


def test_a_childs_items_arrive_in_order_and_it_is_waited_for():
    def items():
        yield os.getpid()
        yield from range(3000)
    got = list(forked(items))
    assert got[0] != os.getpid()            # made in another process
    assert got[1:] == list(range(3000))
    assert gone(got[0])


def test_an_error_that_cannot_cross_is_said_in_words():
    class Local(Exception):     # a local class: pickle cannot name it
        pass

    def items():
        yield 1
        raise Local("the child's own")
    with pytest.raises(RuntimeError, match="Local: the child's own"):
        list(forked(items))


def test_a_child_that_dies_is_one_clear_error():
    def items():
        yield 1
        os._exit(3)
    with pytest.raises(FlowloopError,
                       match=r"ended before the file did \(exit status 3\)"):
        list(forked(items))


def test_a_consumer_that_stops_kills_the_child():
    def endless():
        yield os.getpid()
        k = 0
        while True:
            yield k
            k += 1
    with contextlib.closing(forked(endless, depth=2)) as it:
        pid = next(it)
        with pytest.raises(RuntimeError, match="the consumer's own"):
            for item in it:
                if item == 10:
                    raise RuntimeError("the consumer's own")
    assert gone(pid)
    assert wait_until_gone()        # and the thread that read its pipe


def test_a_closed_iterator_kills_the_child_at_once():
    def endless():
        yield os.getpid()
        while True:
            yield b"x" * 100_000    # fills the pipe: the child blocks on it
    it = forked(endless)
    pid = next(it)
    time.sleep(0.2)
    it.close()
    assert gone(pid, timeout_s=1.0)
    assert wait_until_gone()


def test_a_child_never_asked_is_killed_when_closed_or_dropped():
    def endless():
        while True:
            yield b"x" * 100_000
    for drop in (False, True):
        it = forked(endless)
        pid = it.child.pid
        time.sleep(0.1)         # it fills the pipe and waits on it
        if drop:
            del it              # as a consumer that raised before asking does
        else:
            it.close()
        assert gone(pid, timeout_s=1.0), drop


def test_no_child_where_another_thread_runs():
    release = threading.Event()
    other = threading.Thread(target=release.wait)
    other.start()
    try:
        assert not can_fork()
    finally:
        release.set()
        other.join()
