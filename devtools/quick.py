"""`make test-quick`: the developer's loop.

The unit and c tiers, plus the klippy-tier tests of the klippy modules that
what changed since BASE (default HEAD: the work not yet committed) can
reach: a module in klippy_extras/ changed, or a core module it imports
(directly or through other core modules), or a file of its tests. Klipper
only. `make test` stays the whole truth: every tier, both hosts.
"""

from __future__ import annotations

import argparse
import ast
import os
import subprocess
import sys
from pathlib import Path
from typing import Dict, Iterable, List, Set

PROJECT = Path(__file__).resolve().parent.parent
EXTRAS = PROJECT / "klippy_extras"
KLIPPY_TESTS = PROJECT / "tests" / "klippy"
ALWAYS = ["tests/unit", "tests/c"]


def changed_files(base: str) -> Set[str]:
    """Project-relative paths changed since base, untracked ones included."""
    def git(*args):
        return subprocess.run(["git", "-C", str(PROJECT), *args], check=True,
                              capture_output=True, text=True).stdout.split("\n")
    names = git("diff", "--name-only", base) + git(
        "ls-files", "--others", "--exclude-standard")
    return {name for name in names if name}


def _core_imports(path: Path) -> Set[str]:
    """The flowloop modules path imports, as project-relative files."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: Iterable[str] = ()
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:   # relative: from the file's own package up
                package = path.relative_to(PROJECT).parent.parts
                package = package[:len(package) - node.level + 1]
                module = ".".join([*package, *([module] if module else [])])
            names = [module] + [f"{module}.{a.name}" for a in node.names]
        for name in names:
            if name.split(".")[0] != "flowloop":
                continue
            base = PROJECT.joinpath(*name.split("."))
            for candidate in (base.with_suffix(".py"), base / "__init__.py"):
                if candidate.is_file():
                    found.add(str(candidate.relative_to(PROJECT)))
    return found


def reach(path: str, cache: Dict[str, Set[str]]) -> Set[str]:
    """path and every core module it imports, directly or not."""
    seen, todo = set(), [path]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        if current not in cache:
            cache[current] = _core_imports(PROJECT / current)
        todo.extend(cache[current])
    return seen


def _stem(path: Path) -> str:
    name = path.name.split(".")[0]
    return name[len("test_"):] if name.startswith("test_") else name


def klippy_tests(changed: Set[str]) -> Dict[str, List[str]]:
    """{klippy test file: the changed files that select it}."""
    # a module, or a package (its files together: flow_sensor/)
    extras = sorted(p for p in EXTRAS.iterdir()
                    if (p.suffix == ".py" and p.stem != "__init__")
                    or (p / "__init__.py").is_file())
    tests = sorted(list(KLIPPY_TESTS.glob("test_*.py"))
                   + list(KLIPPY_TESTS.glob("*.test")))
    cache: Dict[str, Set[str]] = {}
    chosen: Dict[str, List[str]] = {}

    def choose(prefix: str, why: Iterable[str]):
        for test in tests:
            if _stem(test).startswith(prefix):
                key = str(test.relative_to(PROJECT))
                chosen.setdefault(key, []).extend(why)

    for extra in extras:
        files = sorted(extra.rglob("*.py")) if extra.is_dir() else [extra]
        reached: Set[str] = set()
        for file in files:
            reached |= reach(str(file.relative_to(PROJECT)), cache)
        why = sorted(reached & changed)
        if why:
            choose(extra.stem, why)
    # a changed test, config or helper of the tier: the tests named like it,
    # down to the module it is about (flow_sensor_cal.cfg: flow_sensor*)
    for name in sorted(changed):
        path = PROJECT / name
        if path.parent != KLIPPY_TESTS or not path.exists():
            continue
        stem = _stem(path)
        owners = [e.stem for e in extras if stem.startswith(e.stem)]
        choose(max(owners, key=len) if owners else stem, [name])
    return chosen


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="make test-quick", description=__doc__)
    parser.add_argument("--base", default="HEAD",
                        help="the commit to compare with (default: HEAD)")
    parser.add_argument("--jobs", default="2", help="pytest-xdist workers")
    args = parser.parse_args(argv)
    changed = changed_files(args.base)
    chosen = klippy_tests(changed)
    print(f"test-quick: {len(changed)} files changed since {args.base}; "
          f"klippy tests on Klipper: {len(chosen) or 'none'}")
    for test, why in chosen.items():
        print(f"  {test}  ({', '.join(sorted(set(why))[:3])})")
    env = {**os.environ, "FLOWLOOP_HOSTS": "klipper"}
    cmd = [sys.executable, "-m", "pytest", "-q", "-n", args.jobs,
           *ALWAYS, *chosen]
    return subprocess.run(cmd, cwd=PROJECT, env=env).returncode


if __name__ == "__main__":
    sys.exit(main())
