"""Helpers for the Moonraker tier: a JSON-RPC websocket client that also
collects notifications (polling is devtools.stack.wait_until), a Moonraker
run from a copy of its package (polling is devtools.stack.wait_until), and
the printer stack a module's tests share (the printer fixture)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import time
from pathlib import Path
from typing import Optional

import pytest

from devtools import spoolman, stack
from flowloop.host import install


class Rpc:
    """A JSON-RPC websocket client that also collects notifications."""

    def __init__(self, url):
        self.url, self.next_id, self.notifications = url, 0, []

    async def __aenter__(self):
        from tornado import websocket
        self.ws = await websocket.websocket_connect(self.url)
        return self

    async def __aexit__(self, *exc):
        self.ws.close()

    async def _read(self, timeout):
        msg = await asyncio.wait_for(self.ws.read_message(), timeout)
        assert msg is not None, "websocket closed"
        return json.loads(msg)

    async def call(self, method, timeout=10.0, **params):
        """The answer to one request, within timeout seconds in all (the
        notifications Moonraker sends every second do not extend it)."""
        self.next_id += 1
        await self.ws.write_message(json.dumps(
            {"jsonrpc": "2.0", "method": method, "params": params, "id": self.next_id}))
        deadline = time.monotonic() + timeout
        while True:
            msg = await self._read(max(0.01, deadline - time.monotonic()))
            # A request that could not be parsed is answered with id null.
            if msg.get("id") == self.next_id or (
                    "error" in msg and msg.get("id") is None):
                return msg
            self.notifications.append(msg)

    async def notification(self, method, timeout=10.0, where=lambda params: True):
        deadline = time.monotonic() + timeout
        while True:
            for msg in self.notifications:
                if msg.get("method") == method and where(msg.get("params")):
                    self.notifications.remove(msg)
                    return msg
            msg = await self._read(max(0.01, deadline - time.monotonic()))
            self.notifications.append(msg)

    async def in_thread(self, fn):
        """A blocking call (an HTTP request, G-code) while the socket listens."""
        return await asyncio.get_running_loop().run_in_executor(None, fn)


@contextlib.contextmanager
def stack_with_cfg(cfg: Optional[str] = None, **options):
    """devtools.stack.printer_stack(**options) on klippy's printer config
    given as text, kept in a temporary file while the stack runs (None:
    config/printer.cfg)."""
    if cfg is None:
        with stack.printer_stack(**options) as ps:
            yield ps
        return
    cfg_dir = stack.short_tempdir("fl-cfg-")
    path = cfg_dir / "test_printer.cfg"
    path.write_text(cfg)
    try:
        with stack.printer_stack(printer_cfg=path, **options) as ps:
            yield ps
    finally:
        shutil.rmtree(cfg_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def printer(request, moonraker_venv):
    """The printer stack a module's tests share, started once per module
    (module scope: make test's scheduler runs the module's tests that use it
    on one worker). What differs between modules, each module says:
    PRINTER_CFG, klippy's printer config, formatted with project= the
    project's folder and PRINTER_CFG_ARGS (none: config/printer.cfg);
    PRINTER_STACK, more printer_stack() arguments (with_klippy=False:
    Moonraker alone, no Klipper wanted); prepare_printer(ps), called once
    the stack is up, before the module's first test."""
    module = request.module
    options = dict(getattr(module, "PRINTER_STACK", {}))
    if options.get("with_klippy", True):
        # Klipper built (skipped without a checkout) and its venv, for klippy
        request.getfixturevalue("klipper_build")
        request.getfixturevalue("klippy_venv")
    cfg = getattr(module, "PRINTER_CFG", None)
    if cfg is not None:
        cfg = cfg.format(project=stack.PROJECT,
                         **getattr(module, "PRINTER_CFG_ARGS", {}))
    with stack_with_cfg(cfg, **options) as ps:
        prepare = getattr(module, "prepare_printer", None)
        if prepare is not None:
            prepare(ps)
        yield ps


@pytest.fixture
def rpc():
    """rpc(port, steps): the result of `await steps(client)`, client an Rpc
    connected to the Moonraker on 127.0.0.1:port."""
    pytest.importorskip("tornado.websocket")

    def run(port, steps):
        async def main():
            async with Rpc(f"ws://127.0.0.1:{port}/websocket") as client:
                return await steps(client)
        return asyncio.run(main())
    return run


def copy_of_moonraker(moonraker_venv, site: Path) -> Path:
    """The test venv's Moonraker package copied to site/moonraker, without
    flowloop; returns site/moonraker."""
    real = install.moonraker_components_dir(moonraker_venv.path).parent
    shutil.copytree(real, site / "moonraker", symlinks=True,
                    ignore=shutil.ignore_patterns("__pycache__", "flowloop",
                                                  "flowloop.py"))
    return site / "moonraker"


@contextlib.contextmanager
def moonraker_from(site: Path, moonraker_venv, prefix: str):
    """Moonraker started from the copy at site (flowloop installed into it
    by the caller), checked to have loaded flowloop from that copy."""
    data_dir = stack.short_tempdir(prefix)
    mr = stack.Moonraker(moonraker_venv, data_dir, moonraker_path=site)
    try:
        mr.wait_ready()
        result = mr.request("GET", "/server/info")[1]["result"]
        assert "flowloop" in result["components"], result
        assert "flowloop" not in result["failed_components"]
        # it ran the copy, not the venv's
        assert str(site / "moonraker") in mr.log_path.read_text()
        yield mr
    finally:
        mr.stop()
        shutil.rmtree(data_dir, ignore_errors=True)


def pytest_terminal_summary(terminalreporter):
    for reason in (spoolman.missing_spoolman_reason(),
                   stack.missing_moonraker_checkout_reason()):
        if reason:
            terminalreporter.write_line("!!! " + reason, red=True, bold=True)
