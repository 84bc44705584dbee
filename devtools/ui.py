"""Mainsail and Fluidd built from the user's checkouts for the ui test tier.

The checkout ($MAINSAIL_PATH / $FLUIDD_PATH, default ~/mainsail, ~/fluidd) is
copied into the cache (keyed by its commit, its local changes and this
file's recipe) and built there with nice -n 10, so the checkout is never
written; only the built dist/ is kept. Two workers never build at once
(one lock per UI). What a build needs here that upstream's does not (a
dependency the npm registry lacks, pnpm 10 for Node 20) is in RECIPES; the
reasons are in docs/ui.md.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Optional

from devtools import stack


@dataclass(frozen=True)
class Ui:
    name: str
    variable: str
    url: str


MAINSAIL = Ui("mainsail", "MAINSAIL_PATH", "https://github.com/mainsail-crew/mainsail")
FLUIDD = Ui("fluidd", "FLUIDD_PATH", "https://github.com/fluidd-core/fluidd")
UIS = {ui.name: ui for ui in (MAINSAIL, FLUIDD)}

# not on the npm registry: the upstream plugin it forks builds both UIs
PLUGIN_VUE2 = "npm:@vitejs/plugin-vue2@2.3.4"
PNPM = "pnpm@10"        # Fluidd pins pnpm 11, which needs Node >= 22.13
BUILD_TIMEOUT_S = 1800


class UiBuildError(RuntimeError):
    """A build that failed: the message is one line, the log beside it."""


def ui_path(ui: Ui) -> Path:
    return Path(os.environ.get(ui.variable, f"~/{ui.name}")).expanduser()


def missing_reason(ui: Ui) -> Optional[str]:
    """Why the ui tier cannot test this UI here, or None."""
    path = ui_path(ui)
    if not (path / "package.json").is_file() or not (path / ".git").exists():
        return (f"no {ui.name.capitalize()} checkout at {path}: the ui tier's "
                f"{ui.name} tests are SKIPPED. Get one with 'git clone {ui.url} "
                f"~/{ui.name}' or set {ui.variable}.")
    for tool in ("node", "npm"):
        if shutil.which(tool) is None:
            return (f"no {tool} on PATH: the ui tier is SKIPPED (Debian: "
                    f"apt-get install nodejs npm).")
    return None


def _git(path: Path, *args: str) -> str:
    return stack._run(["git", "--no-optional-locks", "-C", str(path), *args])


def cache_key(ui: Ui) -> str:
    source = ui_path(ui)
    h = hashlib.sha256()
    for args in (["rev-parse", "HEAD"], ["status", "--porcelain"], ["diff"]):
        h.update(_git(source, *args).encode())
    h.update(inspect.getsource(RECIPES[ui.name]).encode())
    h.update(inspect.getsource(_prepare_common).encode())
    return h.hexdigest()[:16]


def _nice(cmd):
    return ["nice", "-n", "10", *cmd]


def _step(cmd, cwd: Path, log: Path, env: Dict[str, str]) -> None:
    with open(log, "a") as out:
        out.write(f"\n$ {' '.join(cmd)}\n")
        out.flush()
        proc = subprocess.run(_nice(cmd), cwd=cwd, env=env, stdout=out,
                              stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                              timeout=BUILD_TIMEOUT_S)
    if proc.returncode != 0:
        raise UiBuildError(f"'{' '.join(cmd)}' failed ({proc.returncode}); "
                           f"its output is in {log}")


def _edit_json(path: Path, change: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data, indent=2) + "\n")


def _prepare_common(package: dict) -> None:
    package["devDependencies"]["@pedrolamas/plugin-vue2"] = PLUGIN_VUE2


def _build_mainsail(tree: Path, log: Path, env: Dict[str, str]) -> None:
    def change(package):
        _prepare_common(package)
        # vite 8 no longer brings it; the alias's plugin still imports it
        package["devDependencies"]["esbuild"] = "^0.27.0"
    _edit_json(tree / "package.json", change)
    # the alias declares vite <= 7: its peer range cannot be met, hence
    # --legacy-peer-deps (and so npm install, not npm ci)
    _step(["npm", "install", "--legacy-peer-deps", "--no-audit", "--no-fund"],
          tree, log, {**env, "CYPRESS_INSTALL_BINARY": "0"})
    _step(["npx", "--no-install", "vite", "build"], tree, log, env)  # no zip


def _build_fluidd(tree: Path, log: Path, env: Dict[str, str]) -> None:
    _edit_json(tree / "package.json", _prepare_common)
    workspace = tree / "pnpm-workspace.yaml"
    # its catalog names typescript-native-bridge, not on the registry
    workspace.write_text(re.sub(r"(?m)^(\s+typescript:).*$", r"\1 ~5.9.3",
                                workspace.read_text()))
    pnpm = _pnpm(log, env)
    flags = ["--config.manage-package-manager-versions=false"]
    _step([str(pnpm), "install", "--no-frozen-lockfile", *flags], tree, log, env)
    _step([str(pnpm), "run", *flags, "build"], tree, log, env)


RECIPES = {"mainsail": _build_mainsail, "fluidd": _build_fluidd}


def _pnpm(log: Path, env: Dict[str, str]) -> Path:
    prefix = stack.cache_dir() / "pnpm10"
    pnpm = prefix / "node_modules" / ".bin" / "pnpm"
    if not pnpm.exists():
        prefix.mkdir(exist_ok=True)
        _step(["npm", "install", "--prefix", str(prefix), "--no-audit",
               "--no-fund", PNPM], prefix, log, env)
    return pnpm


def _ignore(directory, names):
    return [n for n in names if n in ("node_modules", "dist")]


def build(ui: Ui) -> Path:
    """The built dist/ of the user's checkout of ui (built once per commit and
    local changes, then taken from the cache). Raises UiBuildError in one
    line; a failed build is not tried again for the same key (the error
    names the file to delete to retry)."""
    key = cache_key(ui)
    home = stack.cache_dir() / f"{ui.name}-{key}"
    dist, failed = home / "dist", home.with_name(home.name + ".failed")
    with stack._locked(f"{ui.name}-build"):
        if (home / "ready").exists():
            return dist
        if failed.exists():
            raise UiBuildError(failed.read_text().strip()
                               + f" (delete {failed} to build again)")
        shutil.rmtree(home, ignore_errors=True)
        home.mkdir(parents=True)
        tree, log = home / "src", home / "build.log"
        stack.log(f"building {ui.name} from {ui_path(ui)} in {tree} (minutes)")
        started = time.monotonic()
        shutil.copytree(ui_path(ui), tree, symlinks=True, ignore=_ignore)
        env = {**os.environ, "npm_config_update_notifier": "false",
               "NODE_OPTIONS": "--max-old-space-size=3072"}
        try:
            RECIPES[ui.name](tree, log, env)
            if not (tree / "dist" / "index.html").is_file():
                raise UiBuildError(f"no dist/index.html after the build; see {log}")
        except (UiBuildError, subprocess.TimeoutExpired, OSError) as e:
            failed.write_text(f"{ui.name} build failed: {e}".splitlines()[0])
            shutil.rmtree(tree, ignore_errors=True)
            raise UiBuildError(failed.read_text()) from None
        shutil.move(str(tree / "dist"), dist)
        shutil.rmtree(tree, ignore_errors=True)   # node_modules: ~600 MB each
        (home / "ready").write_text(f"{time.monotonic() - started:.0f} s\n")
        stack.log(f"{ui.name} built in {time.monotonic() - started:.0f} s")
        stack._prune(stack.cache_dir().glob(f"{ui.name}-[0-9a-f]*"), keep=home)
    return dist
