"""A real Spoolman (Donkie/Spoolman) for the moonraker tier, from its source
the way Klipper comes: `git clone https://github.com/Donkie/Spoolman` to
SPOOLMAN_PATH (default ~/spoolman). Never committed, never written to.

Spoolman is not pip-installable from its tree (a flat layout of several
top-level packages); its requirements.txt (uv's export) installs from PyPI
into a virtualenv of its own, cached per requirements text and Python.
Spoolman serves its web client and refuses to start without the client's
build output (client/dist, client_v2/build: npm builds, not in git). These
tests use only its HTTP API, so the harness runs a copy of the server's
source (spoolman/, migrations/, alembic.ini, cached per commit) beside
**placeholder client folders holding one index.html**: the API is the real
one, the web pages are not built. At start-up Spoolman runs `alembic
upgrade head` as a subprocess, so the virtualenv's bin is first on PATH;
its data (SQLite by default) lives in a temporary folder per instance.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

from devtools import stack

SPOOLMAN_URL = "https://github.com/Donkie/Spoolman"
# What the server needs of the tree (the rest is its clients and tooling)
SERVER_PARTS = ("spoolman", "migrations", "alembic.ini", "pyproject.toml")
PLACEHOLDER_CLIENTS = ("client/dist", "client_v2/build")
READY_TIMEOUT_S = 60.0


def spoolman_path() -> Path:
    return Path(os.environ.get("SPOOLMAN_PATH", "~/spoolman")).expanduser()


def missing_spoolman_reason() -> Optional[str]:
    """Why Spoolman cannot run here, in one line, or None."""
    path = spoolman_path()
    how = (f"Get it with 'git clone {SPOOLMAN_URL} ~/spoolman' or set "
           f"SPOOLMAN_PATH.")
    if not (path / "spoolman" / "main.py").is_file() \
            or not (path / "requirements.txt").is_file():
        return (f"no Spoolman source at {path}: the Spoolman tests are "
                f"SKIPPED. {how}")
    return None


def _commit(path: Path) -> str:
    try:
        return subprocess.run(["git", "--no-optional-locks", "-C", str(path),
                               "rev-parse", "HEAD"],
                              capture_output=True, text=True,
                              check=True).stdout.strip()[:12]
    except (subprocess.CalledProcessError, OSError):
        return "nogit"


def spoolman_venv() -> stack.Venv:
    """Spoolman's own virtualenv: its requirements.txt from PyPI."""
    requirements = spoolman_path() / "requirements.txt"
    text = requirements.read_bytes()
    key = hashlib.sha256(text + sys.version.encode()).hexdigest()[:16]
    path = stack.cache_dir() / f"spoolman-venv-{key}"
    venv = stack.Venv(path)
    with stack._locked("spoolman-venv"):
        if (path / ".flowloop-ready").exists():
            return venv
        stack.log(f"building Spoolman's virtualenv from {requirements}")
        shutil.rmtree(path, ignore_errors=True)
        stack._run([sys.executable, "-m", "venv", str(path)])
        stack._run([str(venv.python), "-m", "pip", "install", "-q",
                    "--disable-pip-version-check", "-r", str(requirements)])
        stack._prune(stack.cache_dir().glob("spoolman-venv-*"), keep=path)
        (path / ".flowloop-ready").write_text("ok")
    return venv


def server_tree() -> Path:
    """A runnable copy of Spoolman's server (per commit), with the
    placeholder clients (see the module's docstring)."""
    source = spoolman_path()
    tree = stack.cache_dir() / f"spoolman-{_commit(source)}"
    with stack._locked("spoolman"):
        if (tree / ".flowloop-ready").exists():
            return tree
        tmp = tree.with_name(tree.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for part in SERVER_PARTS:
            src = source / part
            if src.is_dir():
                shutil.copytree(src, tmp / part,
                                ignore=shutil.ignore_patterns("__pycache__"))
            elif src.is_file():
                shutil.copy(src, tmp / part)
        for client in PLACEHOLDER_CLIENTS:
            folder = tmp / client
            folder.mkdir(parents=True)
            (folder / "index.html").write_text(
                "<!doctype html><title>Spoolman</title>"
                "<p>API only: flowloop's test harness does not build the web"
                " client.</p>\n")
        stack._prune(stack.cache_dir().glob("spoolman-[0-9a-f]*"), keep=tmp)
        shutil.rmtree(tree, ignore_errors=True)
        tmp.rename(tree)
        (tree / ".flowloop-ready").write_text("ok")
    return tree


class Spoolman(stack.Process):
    """`uvicorn spoolman.main:app` on 127.0.0.1, its data in data_dir.

    env: more of Spoolman's settings (SPOOLMAN_DB_TYPE and its kin for
    PostgreSQL; see Spoolman's README)."""

    def __init__(self, data_dir: Path, port: Optional[int] = None,
                 env: Optional[Dict[str, str]] = None):
        venv = spoolman_venv()
        tree = server_tree()
        self.port = port or stack.free_port()
        self.data_dir = data_dir
        (data_dir / "logs").mkdir(parents=True, exist_ok=True)
        path = os.pathsep.join([str(venv.path / "bin"), os.environ.get("PATH", "")])
        run_env = {**os.environ, "PATH": path,
                   "SPOOLMAN_DIR_DATA": str(data_dir),
                   "SPOOLMAN_DIR_LOGS": str(data_dir / "logs"),
                   **(env or {})}
        self._start = dict(
            name="spoolman", log_path=data_dir / "logs" / "spoolman.log",
            cmd=[str(venv.python), "-m", "uvicorn", "spoolman.main:app",
                 "--host", "127.0.0.1", "--port", str(self.port)],
            cwd=str(tree), env=run_env)
        super().__init__(**self._start)

    def restart(self) -> None:
        """Stop, then start again on the same port with the same data."""
        self.stop()
        super().__init__(**self._start)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def request(self, method: str, path: str, body: Any = None,
                timeout: float = 10.0) -> Tuple[int, Any]:
        """(status, decoded JSON) of one request to Spoolman's API."""
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(
            self.url + path, data=data, method=method,
            headers={"Content-Type": "application/json"} if data else {})
        try:
            with urllib.request.urlopen(req, timeout=timeout) as resp:
                raw = resp.read()
                return resp.status, json.loads(raw) if raw else None
        except urllib.error.HTTPError as e:
            raw = e.read()
            try:
                return e.code, json.loads(raw)
            except ValueError:
                return e.code, raw.decode(errors="replace")

    def ready(self) -> bool:
        try:
            status, info = self.request("GET", "/api/v1/info", timeout=1.0)
        except (OSError, ValueError):
            return False
        return status == 200 and isinstance(info, dict)

    def wait_ready(self, timeout: float = READY_TIMEOUT_S) -> Dict[str, Any]:
        """Spoolman's /api/v1/info once it answers; RuntimeError (with its
        log's tail) if it stops or does not answer in time."""
        if not stack.wait_until(lambda: not self.alive() or self.ready(),
                                timeout, 0.2) or not self.alive():
            raise RuntimeError(f"Spoolman did not start on port {self.port}:\n"
                               + self.log_tail(2000))
        return self.request("GET", "/api/v1/info")[1]

    # --- the entities the tests need ------------------------------------------
    def add_filament(self, name: str, material: str = "PLA",
                     diameter: float = 1.75, density: float = 1.24,
                     **extra: Any) -> Dict[str, Any]:
        status, filament = self.request("POST", "/api/v1/filament", {
            "name": name, "material": material, "diameter": diameter,
            "density": density, **extra})
        assert status == 200, (status, filament)
        return filament

    def add_spool(self, filament_id: int) -> Dict[str, Any]:
        status, spool = self.request("POST", "/api/v1/spool",
                                     {"filament_id": filament_id})
        assert status == 200, (status, spool)
        return spool
