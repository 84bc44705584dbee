"""Numbers as users type them: G-code parameters, caliper readings, probe
points, speeds; and the check every computed calibration passes before it is
applied.

One reader for a single number (`read_number`, `read_integer`) and one parser
for every comma (or space) separated list (`parse_numbers`), so every G-code
parameter and `flowloop` option accepts the same text: plain decimal digits
(`12`, `-0.5`, `1e-3`), finite. Python's float() also reads `1_000`,
full-width digits, `nan` and `inf`; none of them is a number a user means.
Bad text is refused with one line that names the parameter and its bound:
"LENGTH: must be from 1 to 200, got nan".
"""

from __future__ import annotations

import math
import re
import sys
from typing import Optional, Sequence, Tuple, Union

from .errors import FlowloopError

_SEPARATORS = re.compile(r"[,\s]+")
# ASCII digits only: no '_' separators, no other scripts' digits
_DECIMAL = re.compile(r"[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_INTEGER = re.compile(r"[-+]?[0-9]+")
# Longest text a number may be: more digits than this are a typo or an attack
MAX_NUMBER_CHARS = 40
# A bound "> 0" means a number a computation can divide by: not a subnormal
SMALLEST_ABOVE_ZERO = sys.float_info.min
REQUIRED = object()


class Bounds:
    """Where a number must lie: above/below (exclusive), minimum/maximum
    (inclusive), any of them None. describe() is the phrase a refusal uses."""

    def __init__(self, above: Optional[float] = None,
                 minimum: Optional[float] = None,
                 maximum: Optional[float] = None,
                 below: Optional[float] = None) -> None:
        self.above, self.minimum, self.maximum = above, minimum, maximum
        self.below = below

    def holds(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        if self.above is not None and not value > self.above:
            return False
        if self.above == 0.0 and value < SMALLEST_ABOVE_ZERO:
            return False
        if self.minimum is not None and value < self.minimum:
            return False
        if self.below is not None and not value < self.below:
            return False
        return self.maximum is None or value <= self.maximum

    def describe(self, noun: str = "number") -> str:
        """'above 0', 'above 0 and at most 10', 'above 0 and below 1',
        'a number from 1 to 200', 'at least 1', 'at most 2', 'a finite
        number'."""
        high = (None if self.maximum is None and self.below is None
                else f"below {self.below:g}" if self.below is not None
                else f"at most {self.maximum:g}")
        if self.above is not None:
            low = f"above {self.above:g}"
            return low if high is None else f"{low} and {high}"
        if self.minimum is None:
            return f"a finite {noun}" if high is None else high
        if high is None:
            return f"at least {self.minimum:g}"
        if self.below is not None:
            return f"at least {self.minimum:g} and {high}"
        return f"a {noun} from {self.minimum:g} to {self.maximum:g}"


def shown(text: str) -> str:
    """Typed text as a refusal shows it: as typed when plain, else escaped
    (a full-width digit shows as \\uff11), at most MAX_NUMBER_CHARS."""
    text = str(text)
    if not (text.isascii() and text.isprintable()):
        text = ascii(text)
    if len(text) > MAX_NUMBER_CHARS:
        text = text[:MAX_NUMBER_CHARS - 3] + "..."
    return text or "''"


def _decimal(text: str) -> Optional[float]:
    """The number plain decimal text gives, else None (nan and inf too)."""
    text = text.strip()
    if len(text) > MAX_NUMBER_CHARS or not _DECIMAL.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None


def read_number(text: Optional[str], name: str, default=REQUIRED, *,
                above: Optional[float] = None, minimum: Optional[float] = None,
                maximum: Optional[float] = None, below: Optional[float] = None):
    """One number a user typed (a G-code parameter's text), within bounds.

    text None: the parameter was not given: default (REQUIRED: refused).
    A refusal names the parameter and the bound: "LENGTH: must be above 0,
    got nan"."""
    if text is None:
        if default is REQUIRED:
            raise FlowloopError(f"{name}: missing")
        return default
    bounds = Bounds(above, minimum, maximum, below)
    value = _decimal(str(text))
    if value is None or not bounds.holds(value):
        raise FlowloopError(f"{name}: must be {bounds.describe()}, got"
                            f" {shown(text)}")
    return value


def read_integer(text: Optional[str], name: str, default=REQUIRED, *,
                 minimum: Optional[int] = None, maximum: Optional[int] = None):
    """One whole number a user typed (ENABLE=1, LAYER=3), within bounds."""
    if text is None:
        if default is REQUIRED:
            raise FlowloopError(f"{name}: missing")
        return default
    bounds = Bounds(None, minimum, maximum)
    stripped = str(text).strip()
    if len(stripped) > MAX_NUMBER_CHARS or not _INTEGER.fullmatch(stripped) \
            or not bounds.holds(float(int(stripped))):
        raise FlowloopError(f"{name}: must be {bounds.describe('whole number')},"
                            f" got {shown(text)}")
    return int(stripped)


def check_result(value: float, name: str, *, above: Optional[float] = None,
                 minimum: Optional[float] = None,
                 maximum: Optional[float] = None,
                 below: Optional[float] = None) -> float:
    """A computed value (a calibration's new rotation_distance) checked
    against the bounds of the option it goes into, before it is applied:
    "rotation_distance: must be above 0, got nan"."""
    bounds = Bounds(above, minimum, maximum, below)
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise FlowloopError(f"{name}: must be {bounds.describe()}, got"
                            f" {value!r}") from None
    if not bounds.holds(number):
        raise FlowloopError(f"{name}: must be {bounds.describe()}, got"
                            f" {number:g}")
    return number
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
        value = _part(part, name)
        if positive and value < SMALLEST_ABOVE_ZERO:
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


def _part(part, name: str) -> float:
    """One value of a list: text as read_number reads it, or a number."""
    if isinstance(part, str):
        value = _decimal(part)
        if value is None:
            looks_like = part.strip().lower().lstrip("+-") in ("nan", "inf",
                                                               "infinity")
            what = "is not a finite number" if looks_like else "is not a number"
            raise FlowloopError(f"{name}: '{shown(part)}' {what}")
        return value
    try:
        value = float(part)
    except (TypeError, ValueError):
        raise FlowloopError(f"{name}: '{shown(part)}' is not a number") from None
    if not math.isfinite(value):
        raise FlowloopError(f"{name}: '{part}' is not a finite number")
    return value
