"""klippy as test_missing_requirements.py needs it: run in place of klippy.py (cwd:
the Klipper tree) with numpy hidden from klippy's Python (an import of it
fails, and find_spec does not find it), as on a printer whose klippy-env
never got flowloop's requirements. Everything else is Klipper's own."""

import os
import runpy
import sys

KLIPPY = os.path.join(os.getcwd(), "klippy", "klippy.py")
sys.argv[0] = KLIPPY
if os.path.isfile(os.path.join(os.getcwd(), "klippy", "plugins", "__init__.py")):
    sys.path.insert(0, os.getcwd())    # Kalico: klippy is a package
else:
    sys.path.insert(0, os.path.dirname(KLIPPY))
sys.modules["numpy"] = None   # what `import numpy` finds: nothing
runpy.run_path(KLIPPY, run_name="__main__")
