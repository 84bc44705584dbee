"""Files a command reads and writes: an output never overwrites an input."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence, Tuple

from ..errors import FlowloopError

# (how the user named it: "-o", "--bake", "IN.gcode"; the path, None: not given)
NamedPath = Tuple[str, Optional[Path]]


def same_file(a: Path, b: Path) -> bool:
    """Whether two paths are one file: by the file (./f, a symlink, a hard
    link), not by the string."""
    try:
        return os.path.samefile(a, b)
    except OSError:     # one is not there yet: where it would be
        return os.path.realpath(a) == os.path.realpath(b)


def refuse_overwriting(outputs: Sequence[NamedPath],
                       inputs: Sequence[NamedPath]) -> None:
    """Before anything is written: no output is an input, nor another output."""
    given_inputs = [(name, path) for name, path in inputs if path is not None]
    seen: list = []
    for name, path in outputs:
        if path is None:
            continue
        for other_name, other in given_inputs + seen:
            if same_file(path, other):
                raise FlowloopError(f"{name} {path} would overwrite {other_name}"
                                    f" {other}: write elsewhere")
        seen.append((name, path))
