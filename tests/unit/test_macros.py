"""The shipped macros as Mainsail and Fluidd read them: each parameter's
field pre-filled from a literal |default(...) in the template (the only
place both UIs take a default from), and a description that says what the
macro does (HELP and both UIs show it)."""

from __future__ import annotations

import configparser
import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

MACROS = sorted((Path(__file__).resolve().parents[2] / "macros").glob("*.cfg"))
PARAM = re.compile(r"params\.([A-Z_]+)(\|default\(([^()]*)\))?")
LITERAL = re.compile(r"^('[^']*'|\"[^\"]*\"|-?[0-9.]+)$")


def sections():
    for path in MACROS:
        # read as klippy reads a config file
        parser = configparser.RawConfigParser(strict=False,
                                              inline_comment_prefixes=(";", "#"))
        parser.read(path)
        for name in parser.sections():
            if name.startswith("gcode_macro ") and not name.split()[1].startswith("_"):
                yield path.name, name, dict(parser.items(name))


@pytest.mark.parametrize("path, name, options", list(sections()),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_every_parameter_is_pre_filled_with_a_literal_default(path, name, options):
    gcode = options["gcode"]
    assert "is defined" not in gcode and " in params" not in gcode, name
    assert "params[" not in gcode, name
    for param, has_default, default in PARAM.findall(gcode):
        assert has_default, f"{name}: params.{param} has no |default(...)"
        assert LITERAL.match(default.strip()), (
            f"{name}: params.{param}|default({default}) is no literal a UI can show")


@pytest.mark.parametrize("path, name, options", list(sections()),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_every_macro_has_a_description_a_user_reads(path, name, options):
    description = options.get("description", "")
    assert len(description) >= 40, f"{name}: description too short to read"
    assert description.isascii(), name
