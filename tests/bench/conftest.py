"""`make bench`: figures printed as ratios against a baseline from the same run.

Nothing here asserts a timing; a benchmark fails only if it cannot measure.
`make bench` runs each at its whole size; `make test` runs each at its
smallest (tests/bench/size.py), so a change that breaks a bench fails the
suite, not the next `make bench`.
"""

from __future__ import annotations

import pytest


class BenchReport:
    def __init__(self, terminal):
        self.terminal = terminal

    def ratio(self, name: str, value: float, baseline: float, unit: str = "",
              goal: str = "") -> float:
        """Print value/baseline; goal is the target as text, e.g. '<= 1.0x'."""
        ratio = value / baseline if baseline else float("inf")
        line = (f"BENCH {name}: {value:.6g}{unit} vs baseline {baseline:.6g}{unit}"
                f" = {ratio:.3f}x")
        self.terminal.write_line(line + (f" (goal {goal})" if goal else ""))
        return ratio

    def figure(self, name: str, value: float, unit: str = "", goal: str = "") -> None:
        line = f"BENCH {name}: {value:.6g}{unit}"
        self.terminal.write_line(line + (f" (goal {goal})" if goal else ""))


@pytest.fixture
def bench(request):
    terminal = request.config.pluginmanager.get_plugin("terminalreporter")
    return BenchReport(terminal)
