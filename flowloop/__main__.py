import os
import sys

if not hasattr(sys.modules.get("flowloop"), "__version__") and not (
        getattr(sys.flags, "safe_path", False) or sys.flags.isolated):
    # `python -m` put the working directory first on sys.path and a folder
    # named flowloop/ there (a home holding the clone) was imported as an
    # empty namespace package: run again without the working directory.
    # (-P is processor_check.isolation_flag's: that package is not importable)
    os.execv(sys.executable, [sys.executable,
                              "-P" if sys.version_info >= (3, 11) else "-I",
                              "-m", "flowloop"] + sys.argv[1:])

from .cli import main  # noqa: E402

sys.exit(main())
