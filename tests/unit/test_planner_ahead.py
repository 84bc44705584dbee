"""The planner's batches through a pipe (bulk_planner.write_batch and
read_batch, as flowloop.gcode.ahead's child sends them): the same arrays bit
for bit, of the same types, and the barriers between them, as planning the
file here gives."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from flowloop.errors import FlowloopError
from flowloop.gcode import ahead as ahead_module
from flowloop.gcode import bulk_planner
from flowloop.gcode.ahead import ahead_forked
from flowloop.gcode.bulk_planner import (
    Segments,
    plan_batches,
    planned_ahead,
    read_batch,
    write_batch,
)
from flowloop.gcode.reference_planner import Barrier

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
FILE = DATA / "block_layers_1_2.gcode"


def same_batches(got, want) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert type(g) is type(w)
        if isinstance(w, Barrier):
            assert g == w
            continue
        for name, a, b in zip(Segments._fields, g, w):
            assert a.dtype == b.dtype, name
            # bit for bit: the same bytes, NaN and -0.0 included
            assert a.tobytes() == b.tobytes(), name


def planned_here(path: Path, chunk_bytes: int):
    with open(path, "rb") as f:
        return list(plan_batches(f, chunk_bytes=chunk_bytes))


def test_a_batch_read_back_is_the_batch_written():
    want = planned_here(FILE, 1 << 14)
    assert any(isinstance(b, Barrier) for b in want)
    pipe = io.BytesIO()
    for batch in want:
        write_batch(batch, pipe)
    pipe.seek(0)
    same_batches([read_batch(pipe) for _ in want], want)
    assert pipe.read() == b""


def test_a_batch_cut_short_is_an_error_not_a_shorter_batch():
    batch = next(b for b in planned_here(FILE, 1 << 14) if isinstance(b, Segments))
    pipe = io.BytesIO()
    write_batch(batch, pipe)
    with pytest.raises(FlowloopError, match="in the middle of a batch"):
        read_batch(io.BytesIO(pipe.getvalue()[:-8]))


@pytest.mark.parametrize("chunk_bytes", [1 << 12, 1 << 19])
def test_the_file_planned_in_a_child_is_the_file_planned_here(chunk_bytes):
    def batches():
        with open(FILE, "rb") as f:
            yield from plan_batches(f, chunk_bytes=chunk_bytes)
    got = list(ahead_forked(batches, write_batch, read_batch))
    same_batches(got, planned_here(FILE, chunk_bytes))


@pytest.mark.parametrize("fork, process_from, in_a_child", [
    (True, 0, True),
    (True, FILE.stat().st_size, True),
    (True, FILE.stat().st_size + 1, False),     # too small to be worth it
    (False, 0, False),                          # cannot: another thread runs
])
def test_planned_ahead_in_a_child_or_a_thread(monkeypatch, fork, process_from,
                                              in_a_child):
    monkeypatch.setattr(ahead_module, "can_fork", lambda: fork)
    monkeypatch.setattr(bulk_planner, "PROCESS_FROM_BYTES", process_from)
    children = []

    def spy(*args, **kwargs):
        children.append(args)
        return ahead_forked(*args, **kwargs)
    monkeypatch.setattr(ahead_module, "ahead_forked", spy)
    got = list(planned_ahead(FILE, chunk_bytes=1 << 14))
    same_batches(got, planned_here(FILE, 1 << 14))
    assert bool(children) == in_a_child


def test_a_bad_line_in_a_child_is_the_same_error_after_the_same_batches(tmp_path):
    path = tmp_path / "bad.gcode"
    text = FILE.read_bytes()
    path.write_bytes(text + b"G1 X1 Y1 F1\nG4 P-5\n")
    line = text.count(b"\n") + 2
    message = f"line {line}: P must be >= 0: 'G4 P-5'"
    want = []
    with pytest.raises(FlowloopError, match=message):
        with open(path, "rb") as f:
            for batch in plan_batches(f, chunk_bytes=1 << 14):
                want.append(batch)
    assert want

    def batches():
        with open(path, "rb") as f:
            yield from plan_batches(f, chunk_bytes=1 << 14)
    got = []
    with pytest.raises(FlowloopError, match=message):
        for batch in ahead_forked(batches, write_batch, read_batch):
            got.append(batch)
    same_batches(got, want)
