# flowloop component: the one form of a refusal (one ASCII line).
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import json
from typing import Any


def one_line(msg: Any) -> str:
    """One ASCII line: it becomes an HTTP reason phrase."""
    text = " ".join(str(msg).split()).encode("ascii", "backslashreplace")
    return text.decode()


def quoted(name: str) -> str:
    """A name for a one-line message: JSON-quoted, ASCII only."""
    return json.dumps(name)
