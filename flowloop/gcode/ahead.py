"""An iterator run ahead in a thread: the planner beside its consumer.

`flowloop annotate` and the bake are a two-stage pipeline: the planner
(bulk_planner) turns the file into batches, the melt flow and the annotator
(or the bake's recorder) consume them. Both stages spend most of their time
in numpy, which lets go of the GIL while it works on an array, so on a
machine with a second core the planner runs ahead while the batch before is
consumed (docs/autotemp.md, "Speed"). On one core it costs
a thread switch per batch.

The thread never outlives the consumer's interest: what the iterator raises
is raised in the consumer, in order, after the batches before it; a
consumer that stops early (an error of its own, a generator closed) stops
the thread at its next batch. At most `depth` batches wait between them.
"""

from __future__ import annotations

import queue
import threading
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")
DEPTH = 4
# How often a planner blocked on a full queue looks whether the consumer left.
_POLL_S = 0.05
_END = object()


class _Raised:
    __slots__ = ("error",)

    def __init__(self, error: BaseException):
        self.error = error


def ahead(items: Iterable[T], depth: int = DEPTH) -> Iterator[T]:
    """items, produced in a thread of their own up to depth ahead."""
    waiting: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                waiting.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put(item):
                    return
        except BaseException as e:      # raised in the consumer instead
            put(_Raised(e))
            return
        put(_END)

    thread = threading.Thread(target=produce, name="flowloop-ahead", daemon=True)
    thread.start()
    try:
        while True:
            item = waiting.get()
            if item is _END:
                return
            if isinstance(item, _Raised):
                raise item.error
            yield item
    finally:
        stop.set()
        thread.join()
