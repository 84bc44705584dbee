"""The c tier: mcu_sensor code compiled with the host compiler, warnings fatal."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parents[1]
CFLAGS = ["-std=gnu11", "-O2", "-Wall", "-Wextra", "-Werror"]


@pytest.fixture(scope="module")
def compile_c(tmp_path_factory):
    """compile_c(source in tests/c, *include dirs) -> path of the program."""
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.skip("no host C compiler")

    def build(source: str, *includes: Path) -> Path:
        exe = tmp_path_factory.mktemp("c") / Path(source).stem
        includes = (*includes, PROJECT / "mcu_sensor")
        proc = subprocess.run([cc, *CFLAGS, *(f"-I{d}" for d in includes),
                               str(HERE / source), "-o", str(exe)],
                              capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        return exe
    return build
