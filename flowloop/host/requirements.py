"""What flowloop's klippy sections need in klippy's own Python, asked before
they import the core.

Klipper imports numpy where it is used and turns a missing one into a config
error (shaper_calibrate.py). flowloop's core imports numpy at module load (the
sensor pipeline, grip and the calibrations are vectorised), so the shared
klippy module (klippy_extras/flowloop.py), which every flowloop section
imports before the core, asks here and raises the config error: one line
naming the package and the pip of klippy's Python that installs it. Nothing
is imported to find out (find_spec): a printer that has them all pays
nothing for the question. This module imports the standard library only.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import Optional

# pyproject.toml's dependencies, by the name they are imported as (a unit
# test keeps the two lists equal)
REQUIREMENTS = ("numpy", "scipy", "msgspec", "jinja2")


def missing(python: str = sys.executable) -> Optional[str]:
    """The one-line error for the first requirement this Python cannot
    import, None when it has them all."""
    for module in REQUIREMENTS:
        if importlib.util.find_spec(module) is None:
            return missing_message(module, python)
    return None


def missing_message(module: str, python: str) -> str:
    pip = Path(python).with_name("pip")
    return (f"klippy's Python ({python}) has no {module}, which flowloop needs:"
            f" run {pip} install {module} (or {pip} install klipper-flowloop for"
            f" all it needs)")
