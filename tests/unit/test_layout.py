"""The core's layout: domains import each other and errors, never the CLI or a host."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

CORE = Path(__file__).resolve().parents[2] / "flowloop"
HOSTS = ("klippy", "extras", "moonraker", "configfile", "gcode", "reactor")


def imported_modules(path: Path):
    """Absolute names of what one core file imports (relative imports resolved)."""
    package = ".".join(path.relative_to(CORE.parent).with_suffix("").parts[:-1])
    if path.name == "__init__.py":
        package = ".".join(path.relative_to(CORE.parent).parts[:-1])
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            yield module
            yield from (f"{module}.{alias.name}" for alias in node.names)


def domain_files():
    return [p for p in CORE.rglob("*.py") if "cli" not in p.relative_to(CORE).parts]


# Beside the domain folders only the shared leaves every domain imports
# downward: the error type, whole-or-nothing file writes, number parsing,
# the depth of outside JSON,
# the grip window.
SHARED_LEAVES = ["errors.py", "files.py", "nesting.py", "numbers.py", "window.py"]


def test_the_core_is_grouped_into_domain_folders():
    flat = sorted(p.name for p in CORE.glob("*.py"))
    assert flat == ["__init__.py", "__main__.py"] + SHARED_LEAVES
    for folder in ("sensor", "material", "calibrate", "host", "cli"):
        assert (CORE / folder / "__init__.py").is_file(), folder


def test_no_domain_imports_the_cli():
    offenders = [f"{p.relative_to(CORE)} imports {m}" for p in domain_files()
                 if p.name != "__main__.py"
                 for m in imported_modules(p) if m.startswith("flowloop.cli")]
    assert offenders == []


def test_the_core_imports_no_host():
    offenders = [f"{p.relative_to(CORE)} imports {m}" for p in CORE.rglob("*.py")
                 for m in imported_modules(p) if m.split(".")[0] in HOSTS]
    assert offenders == []


def test_relative_imports_are_resolved_against_the_package():
    # The check above is only as good as this resolution.
    mods = set(imported_modules(CORE / "cli" / "delta.py"))
    assert "flowloop.calibrate.delta" in mods
    assert "flowloop.errors.FlowloopError" in mods


def test_the_shared_leaves_import_no_domain():
    offenders = [f"{name} imports {m}" for name in SHARED_LEAVES
                 for m in imported_modules(CORE / name)
                 if m.startswith("flowloop.")
                 and not m.startswith(("flowloop.errors", "flowloop.numbers"))]
    assert offenders == []


def test_no_core_module_imports_another_modules_private_names():
    # A seam between two modules is public: the bulk planner reaches the
    # reference planner through Move, Planner's queue_move/flush_queue and
    # HANDLED_COMMANDS, not through _Move or Planner._handlers.
    offenders = [f"{p.relative_to(CORE)} imports {m}" for p in domain_files()
                 for m in imported_modules(p)
                 if m.startswith("flowloop.") and any(
                     part.startswith("_") and not part.startswith("__")
                     for part in m.split(".")[1:])]
    assert offenders == []


def test_the_two_planners_say_which_is_the_reference():
    gcode = CORE / "gcode"
    assert sorted(p.name for p in gcode.glob("*planner*.py")) == [
        "bulk_planner.py", "reference_planner.py"]
    mods = set(imported_modules(gcode / "bulk_planner.py"))
    assert "flowloop.gcode.reference_planner.Planner" in mods
    assert not any(m.startswith("flowloop.gcode.bulk_planner")
                   for m in imported_modules(gcode / "reference_planner.py"))


# The domains from the top floor down: a module imports its own domain and
# those below it, never one above (farm-studio look: no arrow back up). The
# domains of one floor import none of each other.
FLOORS = [("cli",), ("calibrate",), ("host",), ("sensor", "gcode"), ("control",),
          ("report",), ("material",)]


def floor_of(domain: str) -> int:
    return next(i for i, floor in enumerate(FLOORS) if domain in floor)


def test_the_domains_import_only_downward():
    offenders = []
    for path in CORE.rglob("*.py"):
        parts = path.relative_to(CORE).parts
        if len(parts) < 2:
            continue
        for m in imported_modules(path):
            target = m.split(".")
            if (target[0] != "flowloop" or len(target) < 2
                    or target[1] == parts[0]
                    or not any(target[1] in floor for floor in FLOORS)):
                continue
            if floor_of(target[1]) <= floor_of(parts[0]):
                offenders.append(f"{path.relative_to(CORE)} imports {m}")
    assert offenders == []


def test_every_domain_folder_has_its_floor():
    folders = {p.name for p in CORE.iterdir() if (p / "__init__.py").is_file()}
    assert folders == {d for floor in FLOORS for d in floor}
