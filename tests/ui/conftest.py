"""The ui tier: Mainsail and Fluidd built from the user's checkouts
(devtools/ui.py), served as the usual nginx serves them (devtools/ui_proxy.py)
against the moonraker tier's printer stack, in headless Chromium. Without a
checkout, node or a build that succeeds, a UI's tests are skipped with one
loud line."""

from __future__ import annotations

import sys
from typing import Dict

import pytest

from devtools import browser as browser_tools
from devtools import stack, ui
from tests.moonraker.conftest import printer  # noqa: F401  (the shared stack)

_BUILD_FAILURES: Dict[str, str] = {}


def built(name: str):
    """The UI's dist/, built once per checkout commit; skips with its reason."""
    spec = ui.UIS[name]
    reason = ui.missing_reason(spec) or _BUILD_FAILURES.get(name)
    if reason:
        pytest.skip(reason)
    try:
        return ui.build(spec)
    except ui.UiBuildError as e:
        _BUILD_FAILURES[name] = f"{e}: the ui tier's {name} tests are SKIPPED"
        pytest.skip(_BUILD_FAILURES[name])


class Served:
    """A built UI and the printer's Moonraker on one origin."""

    def __init__(self, name: str, dist, moonraker_port: int, workdir):
        self.name = name
        self.port = stack.free_port()
        self.proc = stack.Process(
            f"{name}-proxy", [sys.executable, "-m", "devtools.ui_proxy",
                              str(self.port), str(dist), str(moonraker_port)],
            workdir / f"{name}-proxy.log", cwd=str(stack.PROJECT))
        if not stack.wait_until(lambda: self._up() or not self.proc.alive(), 20) \
                or not self.proc.alive():
            raise RuntimeError(f"{name}'s server did not start:\n"
                               + self.proc.log_tail())

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _up(self) -> bool:
        import urllib.request
        try:
            with urllib.request.urlopen(self.url + "/index.html", timeout=2):
                return True
        except OSError:
            return False


def chrome():
    """Headless Chromium as tests/moonraker/test_page.py drives it (the
    browser's log kept for its JavaScript errors)."""
    reason = browser_tools.missing_reason()
    if reason:
        pytest.skip(reason)
    return browser_tools.chrome(1400, 1000)


def pytest_terminal_summary(terminalreporter):
    for spec in ui.UIS.values():
        reason = ui.missing_reason(spec) or _BUILD_FAILURES.get(spec.name)
        if reason:
            terminalreporter.write_line("!!! " + reason, red=True, bold=True)
