# flowloop component: the one form of a refusal (one printable ASCII line).
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import json
import re
from typing import Any

# What one_line escapes: anything but printable ASCII (whitespace is already
# one space by then).
_UNPRINTABLE = re.compile(r"[^\x20-\x7e]")


def _escape(match: re.Match) -> str:
    code = ord(match.group())
    return f"\\x{code:02x}" if code < 0x100 else \
        f"\\u{code:04x}" if code < 0x10000 else f"\\U{code:08x}"


def one_line(msg: Any) -> str:
    """One line of printable ASCII (runs of whitespace as one space, any other
    character as its Python escape) without `<`, which is written `\\u003c`
    as JSON writes it (a JSON-quoted name still decodes whole): the same
    text reaches a JSON-RPC client, the JSON body of an HTTP error and its
    reason phrase. Moonraker answers an HTTP error with the reason phrase as
    the body's message, and tornado (>= 6.5) replaces a phrase holding `<`
    by "Unknown" (docs/reference.md, "Refusals")."""
    return _UNPRINTABLE.sub(_escape, " ".join(str(msg).split())).replace(
        "<", "\\u003c")


def quoted(name: str) -> str:
    """A name for a one-line message: JSON-quoted, ASCII only."""
    return json.dumps(name)
