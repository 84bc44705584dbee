"""devtools/realtime_klippy.py's exit: batch-mode klippy waits until its
serial queue has written what it holds (the Kalico runs that lost their last
seconds of steps beside busy processes)."""

from __future__ import annotations

import threading
import time

from devtools import realtime_klippy

KLIPPER_STATS = ("bytes_write=120 bytes_read=0 bytes_retransmit=0 bytes_invalid=0"
                 " send_seq=9 receive_seq=-1 retransmit_seq=0 srtt=0.000"
                 " rttvar=0.000 rto=0.025 ready_bytes={} upcoming_bytes={}")


def test_the_queued_bytes_are_read_from_the_stats_line():
    assert realtime_klippy.queued_bytes(KLIPPER_STATS.format(195, 0)) == 195
    assert realtime_klippy.queued_bytes(KLIPPER_STATS.format(10, 32)) == 42
    assert realtime_klippy.queued_bytes(KLIPPER_STATS.format(0, 0)) == 0
    assert realtime_klippy.queued_bytes("") == 0   # the queue already freed


class Reader:
    """A serial reader whose queue's thread writes its bytes a while later."""

    def __init__(self, queued: int, write_after_s: float):
        self.serialqueue = object()
        self.queued = queued
        self.left_at_disconnect = None
        timer = threading.Timer(write_after_s, self.write)
        timer.daemon = True
        timer.start()

    def write(self):
        self.queued = 0

    def stats(self, eventtime):
        return KLIPPER_STATS.format(self.queued, 0)

    def disconnect(self):
        self.left_at_disconnect = self.queued


def test_disconnect_waits_for_the_queue_to_be_written():
    class Drained(Reader):
        pass
    realtime_klippy.drain_on_disconnect(Drained)
    reader = Drained(939, write_after_s=0.2)
    started = time.monotonic()
    reader.disconnect()
    assert reader.left_at_disconnect == 0
    assert time.monotonic() - started >= 0.15
    # without the drain the same queue is cut off
    plain = Reader(939, write_after_s=0.2)
    plain.disconnect()
    assert plain.left_at_disconnect == 939


def test_a_queue_that_never_empties_does_not_hold_the_exit_for_ever(monkeypatch):
    monkeypatch.setattr(realtime_klippy, "DRAIN_TIMEOUT_S", 0.1)

    class Stuck(Reader):
        pass
    realtime_klippy.drain_on_disconnect(Stuck)
    reader = Stuck(64, write_after_s=30.0)
    reader.disconnect()
    assert reader.left_at_disconnect == 64
