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
    character as its Python escape): the same text reaches a JSON-RPC client,
    the JSON body of an HTTP error and, but for `<`, its reason phrase."""
    return _UNPRINTABLE.sub(_escape, " ".join(str(msg).split()))


def reason_phrase(line: str) -> str:
    """An HTTP reason phrase tornado sends as it is: one_line's text, with `<`
    (which tornado replaces the whole phrase for, "Unknown") as `\\x3c`."""
    return one_line(line).replace("<", "\\x3c")


def quoted(name: str) -> str:
    """A name for a one-line message: JSON-quoted, ASCII only."""
    return json.dumps(name)
