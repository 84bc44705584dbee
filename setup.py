"""Build hook: a wheel carries what `flowloop install` links.

pyproject.toml holds the metadata. The klippy modules, the Moonraker
component and the MCU sources live beside the package in a checkout; a built
wheel carries a copy of them in flowloop/_hosts/ (flowloop.host.install
.source_tree() finds either). An editable install needs no copy.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
# folder -> the files of it a host loads (MANIFEST.in puts them in the sdist)
HOST_FILES = {
    "klippy_extras": ("**/*.py",),   # modules and packages (flow_sensor/)
    "moonraker_components": ("**/*.py",),
    "mcu_sensor": ("*.c", "*.h"),
}
BUNDLE = ("flowloop", "_hosts")


class BuildPy(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return
        dest_root = Path(self.build_lib, *BUNDLE)
        for folder, patterns in HOST_FILES.items():
            for pattern in patterns:
                for src in sorted((ROOT / folder).glob(pattern)):
                    if "__pycache__" in src.parts:
                        continue
                    dest = dest_root / folder / src.relative_to(ROOT / folder)
                    self.mkpath(str(dest.parent))
                    self.copy_file(str(src), str(dest))


setup(cmdclass={"build_py": BuildPy})
