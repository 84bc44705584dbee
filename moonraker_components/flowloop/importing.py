# flowloop component: the installed flowloop package, whatever Moonraker's
# working directory holds.
#
# `python -m moonraker` puts the working directory first on sys.path, and a
# folder named flowloop/ there (a home holding the clone, with flowloop
# installed editable) is then imported as an empty namespace package: every
# `from flowloop...` of the component fails. Imported first by the component,
# this imports the package again without that entry where that happened; later
# imports find it in sys.modules.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import importlib
import os
import sys


def import_installed_flowloop() -> None:
    module = importlib.import_module("flowloop")
    if hasattr(module, "__version__"):
        return
    for name in [n for n in sys.modules if n == "flowloop"
                 or n.startswith("flowloop.")]:
        del sys.modules[name]
    cwd = os.getcwd()
    saved = list(sys.path)
    sys.path[:] = [p for p in saved if os.path.abspath(p or os.curdir) != cwd]
    try:
        importlib.import_module("flowloop")
    finally:
        sys.path[:] = saved


import_installed_flowloop()
