"""Lists of numbers as users type them: caliper readings, probe points, speeds.

One parser for every comma (or space) separated list a G-code parameter or a
`flowloop` option takes, so they all accept the same text and refuse bad text
with the same one-line message, naming the parameter.
"""

from __future__ import annotations

import math
import re
from typing import Optional, Sequence, Tuple, Union

from .errors import FlowloopError

_SEPARATORS = re.compile(r"[,\s]+")
# "9,9": one number with a decimal comma (as typed in much of Europe), or two?
_DECIMAL_COMMA = re.compile(r"[-+]?\d+,\d+")


def parse_numbers(text: Union[str, Sequence[float]], name: str, *,
                  what: str = "value", count: Optional[int] = None,
                  minimum_count: int = 1, positive: bool = False,
                  decimal_comma_refused: bool = False) -> Tuple[float, ...]:
    """'150.12, 150.14,150.1' -> (150.12, 150.14, 150.1), all finite.

    text: commas and/or spaces between numbers (a trailing comma is fine), or
    a sequence of numbers. name: the parameter or option, first in every
    message; what: one value's name in messages ("reading", "speed").
    count: exactly this many values; minimum_count: at least this many;
    positive: every value above 0. decimal_comma_refused: values that are
    rarely whole (caliper readings): "9,9" in a text without a dot is refused
    as a likely 9.9 typed with a decimal comma, not read as two values.
    """
    if isinstance(text, str):
        parts = [p for p in _SEPARATORS.split(text.strip()) if p]
    else:
        parts = list(text)
    if not parts:
        raise FlowloopError(f"{name}: no {what}s given")
    if decimal_comma_refused and isinstance(text, str):
        _refuse_decimal_comma(text, name, what)
    values = []
    for part in parts:
        try:
            value = float(part)
        except (TypeError, ValueError):
            raise FlowloopError(f"{name}: '{part}' is not a number") from None
        if not math.isfinite(value):
            raise FlowloopError(f"{name}: '{part}' is not a finite number")
        if positive and value <= 0.0:
            raise FlowloopError(f"{name}: {what} {part} must be positive")
        values.append(value)
    if count is not None and len(values) != count:
        plural = "" if count == 1 else "s"
        raise FlowloopError(f"{name}: needs {count} {what}{plural}, got {len(values)}")
    if len(values) < minimum_count:
        raise FlowloopError(f"{name}: needs at least {minimum_count} {what}s,"
                            f" got {len(values)}")
    return tuple(values)


def _two(word: str) -> str:
    """'9,9' as two values that cannot be misread: '9.0,9.0'."""
    return ",".join(f"{part}.0" for part in word.split(","))


def _refuse_decimal_comma(text: str, name: str, what: str) -> None:
    """Without a dot anywhere, "9,9" (no space after the comma) may be 9.9
    typed as much of Europe writes it, or two values: refuse to guess."""
    if "." in text:
        return
    for word in text.split():
        if _DECIMAL_COMMA.fullmatch(word):
            raise FlowloopError(f"{name}: '{word}' has a decimal comma: write"
                                f" {word.replace(',', '.')}, or separate {what}s"
                                f" with spaces (or dots: {_two(word)})")
