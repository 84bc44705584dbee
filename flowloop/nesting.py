"""How deep JSON from outside nests, found without recursion.

Python's json (and code that walks what it returns) recurses once per level:
a document a few thousand levels deep raises RecursionError, which no caller
expects. Text from outside (a request body, a Spoolman extra field) is
measured here first and refused past MAX_JSON_DEPTH; nothing flowloop stores
nests more than a few levels.
"""

from __future__ import annotations

import re
from typing import Union

import numpy as np

from .errors import FlowloopError

MAX_JSON_DEPTH = 64
# A JSON string, or an unterminated one to the end of the text: each
# character is consumed once, so the scan stays linear on any input.
_STRING = re.compile(r'"(?:[^"\\]|\\.)*+"?', re.DOTALL)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")


def json_depth(text: Union[str, bytes]) -> int:
    """The deepest nesting of objects and arrays in JSON text (brackets
    inside strings not counted), valid JSON or not: linear, in C."""
    if isinstance(text, (bytes, bytearray)):
        text = bytes(text).decode("utf-8", errors="replace")
    brackets = _NOT_BRACKET.sub("", _STRING.sub("", text))
    if not brackets:
        return 0
    codes = np.frombuffer(brackets.encode("ascii"), dtype=np.uint8)
    steps = np.where((codes == ord("[")) | (codes == ord("{")), 1, -1)
    return int(max(0, np.cumsum(steps).max()))


def check_json_depth(text: Union[str, bytes], what: str,
                     limit: int = MAX_JSON_DEPTH) -> None:
    """FlowloopError (one line naming `what`) for JSON nested deeper than
    `limit`."""
    depth = json_depth(text)
    if depth > limit:
        raise FlowloopError(f"{what} nests {depth} levels deep; at most "
                            f"{limit} are read")
