"""How big a benchmark runs: whole under `make bench`, smallest under `make test`.

`make bench` sets FLOWLOOP_BENCH_SIZE=full and every figure is measured on
the whole workload. Anywhere else (`make test`, a plain `pytest`) each bench
runs at its smallest size: a smoke run that checks it still executes and
prints its figures, so an API change cannot break a bench unseen. The
figures of a smoke run mean nothing and nothing judges them.
"""

from __future__ import annotations

import os

FULL = os.environ.get("FLOWLOOP_BENCH_SIZE", "") == "full"


def pick(full, smoke):
    """full under `make bench`, smoke anywhere else."""
    return full if FULL else smoke
