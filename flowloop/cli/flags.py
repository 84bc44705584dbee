"""The core names its fields (max_power_w); the user typed flags (--heater-power)."""

from __future__ import annotations

from typing import Iterable, Sequence

from ..errors import FlowloopError


def with_flags(error: FlowloopError, table: Iterable[Sequence[str]]) -> FlowloopError:
    """error's message with each field named by its flag; table rows start
    (flag without dashes, field)."""
    text = str(error)
    for flag, field, *_ in table:
        text = text.replace(field, f"--{flag}")
    return FlowloopError(text)
