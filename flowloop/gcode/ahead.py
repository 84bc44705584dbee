"""An iterator run ahead of its consumer: the planner beside the annotator.

`flowloop annotate` and the bake are a two-stage pipeline: the planner
(bulk_planner) turns the file into batches, the melt flow and the annotator
(or the bake's recorder) consume them. On a machine with a second core the
planner runs ahead while the batch before is consumed (docs/autotemp.md,
"Speed"):

- `ahead_forked` runs it in a child process (os.fork) that sends each item
  through a pipe, encoded by the caller (bulk_planner.write_batch: a batch's
  arrays as their raw bytes), and a thread here reads them as they come.
  Two processes do not share a GIL: on the 25 MB bench file the whole
  `flowloop annotate` took 0.88x to 0.96x the time it took with the planner
  in a thread, whose numpy calls wait for each other's Python between
  arrays. Without the reading thread it gained nothing: the pipe holds
  less than a batch, and the child waited for the annotator to ask for
  each.
- `ahead` runs it in a thread: the fallback where forking is not safe (a
  process with threads already: a lock one of them holds would stay held in
  the child), not possible (no os.fork) or no use (one core, where a thread
  costs a switch per batch and a process a copy of every batch as well).
  `ahead_of` chooses; its caller says whether the work is worth a process
  (bulk_planner.planned_ahead: a file of 4 MiB or more).

Neither outlives the consumer's interest: what the iterator raises is
raised in the consumer, in order, after the items before it; a consumer
that stops early (an error of its own, a generator closed) stops the thread
at its next item, or kills the child (then the thread). At most `depth`
items wait between them, and a pipe's buffer more from a child.
"""

from __future__ import annotations

import os
import pickle
import queue
import signal
import struct
import threading
from typing import BinaryIO, Callable, Iterable, Iterator, Optional, TypeVar

from ..errors import FlowloopError

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
        finally:
            # a generator's own cleanup (its open file) runs here and now
            close = getattr(items, "close", None)
            if close is not None:
                close()
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


# --- in a child process ---------------------------------------------------------

# the pipe's buffer: a batch of the bench file is about 1.4 MB of arrays,
# the kernel's 64 kB default would switch between the two every 64 kB
_PIPE_BYTES = 1 << 20
# Linux's fcntl command for it (Python names it fcntl.F_SETPIPE_SZ from 3.10)
_F_SETPIPE_SZ = 1031
# each message: what it is, and its length (or the items' count)
_HEADER = struct.Struct("<cq")
_SENT, _RAISED_THERE, _DONE = b"I", b"R", b"Z"


def can_fork() -> bool:
    """Whether ahead_forked is safe and of use here: os.fork and pidfds
    exist (Linux), this process has no other thread, and it may run on
    two cores."""
    if not hasattr(os, "fork") or not hasattr(os, "pidfd_open") \
            or threading.active_count() != 1:
        return False
    cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
             else os.cpu_count() or 1)
    if cores < 2:
        return False
    try:                                # a kernel older than 5.3 has none
        os.close(os.pidfd_open(os.getpid()))
    except OSError:
        return False
    return True


def ahead_of(make_items: Callable[[], Iterable[T]],
             write_item: Callable[[T, BinaryIO], None],
             read_item: Callable[[BinaryIO], T], depth: int = DEPTH,
             worth_a_process: bool = True) -> Iterator[T]:
    """make_items()'s items run ahead in a child process where the caller
    says the work is worth one and can_fork(), else in a thread."""
    if worth_a_process and can_fork():
        return ahead_forked(make_items, write_item, read_item, depth)
    return ahead(iter(make_items()), depth)


def ahead_forked(make_items: Callable[[], Iterable[T]],
                 write_item: Callable[[T, BinaryIO], None],
                 read_item: Callable[[BinaryIO], T],
                 depth: int = DEPTH) -> Iterator[T]:
    """make_items()'s items, made in a child process: write_item(item, pipe)
    there, read_item(pipe) here (it reads exactly what write_item wrote).
    Here a thread reads them as they come, up to depth ahead: the pipe's
    buffer holds less than a batch, and a child that waited for this
    process to ask for each would plan only as fast as it is consumed."""
    read_fd, write_fd = os.pipe()
    try:
        import fcntl
        fcntl.fcntl(write_fd, _F_SETPIPE_SZ, _PIPE_BYTES)
    except (ImportError, OSError):
        pass            # the default buffer: slower, no less right
    pid = os.fork()
    if pid == 0:                                    # the child
        os.close(read_fd)
        _produce(make_items, write_item, write_fd)  # never returns
    os.close(write_fd)
    return _Forked(_Child(pid), os.fdopen(read_fd, "rb"), read_item, depth)


class _Child:
    """The child process, through a pidfd: a signal never reaches another
    process that took its pid after it ended."""

    def __init__(self, pid: int):
        self.pid = pid
        self.pidfd = os.pidfd_open(pid)
        self.status: Optional[int] = None
        self.lock = threading.Lock()

    def kill(self) -> None:
        try:
            signal.pidfd_send_signal(self.pidfd, signal.SIGKILL)
        except ProcessLookupError:      # ended and waited for
            pass

    def ended(self) -> str:
        """Wait for it (once) and say how it ended."""
        with self.lock:
            if self.status is None:
                _, self.status = os.waitpid(self.pid, 0)
        if os.WIFSIGNALED(self.status):
            return f"killed by signal {os.WTERMSIG(self.status)}"
        return f"exit status {os.WEXITSTATUS(self.status)}"


class _Forked:
    """The child's items, read by a thread here (flowloop.gcode.ahead's
    `ahead` over the pipe). close() ends the child, then the thread, then
    the pipe, whether iteration began or not; the last item, an error
    raised or a close does it, and so does dropping the iterator."""

    def __init__(self, child: _Child, pipe: BinaryIO, read_item, depth: int):
        self.child, self.pipe = child, pipe
        self.items = ahead(_received(child, pipe, read_item), depth)
        self.closed = False

    def __iter__(self) -> _Forked:
        return self

    def __next__(self):
        try:
            return next(self.items)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        # the child goes first: the thread's read then ends at once, and
        # joining it never waits on the child's next write
        self.child.kill()
        self.items.close()
        self.pipe.close()
        self.child.ended()
        os.close(self.child.pidfd)

    def __del__(self) -> None:
        if getattr(self, "items", None) is not None:    # made whole
            self.close()


def _produce(make_items, write_item, write_fd: int) -> None:
    status = 0
    try:
        # Ctrl-C reaches the whole process group: the parent stops, and
        # with it the pipe, which ends this at its next write
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with os.fdopen(write_fd, "wb", buffering=_PIPE_BYTES) as pipe:
            try:
                for item in make_items():
                    pipe.write(_HEADER.pack(_SENT, 0))
                    write_item(item, pipe)
            except BaseException as e:      # raised in the consumer instead
                _send_raised(pipe, e)
            else:
                pipe.write(_HEADER.pack(_DONE, 0))
    except BaseException:
        status = 1          # the pipe closed: the consumer left
    finally:
        # no cleanup of the parent's: its buffers, atexit, open files
        os._exit(status)


def _send_raised(pipe: BinaryIO, error: BaseException) -> None:
    try:
        data = pickle.dumps(error)
        pickle.loads(data)
    except Exception:
        data = pickle.dumps(RuntimeError(f"{type(error).__name__}: {error}"))
    pipe.write(_HEADER.pack(_RAISED_THERE, len(data)))
    pipe.write(data)


def _received(child: _Child, pipe: BinaryIO, read_item) -> Iterator:
    """The items the child sends, then what it raised, if anything."""
    while True:
        header = pipe.read(_HEADER.size)
        if len(header) < _HEADER.size:
            raise FlowloopError("the planner's process ended before"
                                f" the file did ({child.ended()})")
        kind, size = _HEADER.unpack(header)
        if kind == _SENT:
            yield read_item(pipe)
        elif kind == _RAISED_THERE:
            raise pickle.loads(read_exactly(pipe, size))
        else:
            return


def read_exactly(pipe: BinaryIO, size: int) -> bytes:
    """size bytes from pipe, or an error if it ends first."""
    data = pipe.read(size)
    if len(data) != size:
        raise FlowloopError("the planner's process ended in the middle of a batch")
    return data


def read_into(pipe: BinaryIO, buffer) -> None:
    """Fill buffer (a writable bytes-like object) from pipe."""
    view = memoryview(buffer).cast("B")
    got = 0
    while got < len(view):
        n = pipe.readinto(view[got:])
        if not n:
            raise FlowloopError("the planner's process ended in the middle of a batch")
        got += n
