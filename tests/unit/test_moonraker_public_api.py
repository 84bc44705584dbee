"""The Moonraker component uses Moonraker's public calls only (issue 39.1):
what it imports from Moonraker are the modules a component is given to
use, never the application's router or request handlers, and it reaches
into no other object's private attributes. Moonraker's internals change
between releases (the git checkout KIAUH installs is not the PyPI one)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

COMPONENT = Path(__file__).resolve().parents[2] / "moonraker_components" / "flowloop"
# what Moonraker's own components import from it (spoolman.py, history.py)
# (the components only for type hints of what lookup_component returns)
PUBLIC_MODULES = {"common", "confighelper", "server", "utils",
                  "components.database", "components.klippy_apis",
                  "components.klippy_connection"}
# what it takes from moonraker.common, each what Moonraker hands a component
# or asks of one: the request's types and errors of register_endpoint, and
# HistoryFieldData, the one argument history.register_auxiliary_field takes
# (Moonraker's own sensor and spoolman components build theirs with it; no
# other way in exists in 0.11 or the git checkout)
COMMON_NAMES = {"RequestType", "TransportType", "WebRequest", "ServerError",
                "HistoryFieldData"}
INTERNALS = {"application", "mutable_router", "pattern_to_rule",
             "DynamicRequestHandler", "RequestHandler", "add_handler",
             "get_handler_delegate"}


def modules():
    return sorted(COMPONENT.glob("*.py"))


def moonraker_imports(tree):
    """(module, names) of every import from Moonraker, named from the
    moonraker package (the component is moonraker.components.flowloop: two
    dots are moonraker.components, three the moonraker package)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level >= 2:
            prefix = "components." if node.level == 2 else ""
            yield prefix + (node.module or ""), [a.name for a in node.names]


@pytest.mark.parametrize("path", modules(), ids=lambda p: p.name)
def test_only_moonrakers_public_modules_are_imported(path):
    tree = ast.parse(path.read_text())
    for module, names in moonraker_imports(tree):
        assert module in PUBLIC_MODULES, (path.name, module)
        if module == "common":
            assert set(names) <= COMMON_NAMES, (path.name, names)
        assert not INTERNALS & set(names), (path.name, names)


@pytest.mark.parametrize("path", modules(), ids=lambda p: p.name)
def test_no_router_rule_or_private_attribute_of_another_object(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            assert node.attr not in INTERNALS | {"target"}, (path.name, node.lineno)
            private = node.attr.startswith("_") and not node.attr.startswith("__")
            owner = node.value.id if isinstance(node.value, ast.Name) else None
            assert not private or owner in ("self", "cls"), (path.name, node.lineno,
                                                             node.attr)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
                and node.func.id in ("getattr", "setattr") and len(node.args) > 1 \
                and isinstance(node.args[1], ast.Constant):
            name = str(node.args[1].value)
            assert name not in INTERNALS and not name.startswith("_"), (
                path.name, node.lineno, name)
