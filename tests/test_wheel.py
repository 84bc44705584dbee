"""The released form: a wheel and an sdist, each pip-installed into a fresh
virtualenv, give a `flowloop` whose installer links everything it links from
a checkout (klippy modules, the Moonraker component package, the MCU sources)
and whose commands find their templates.

Built from a copy of this tree (a build writes build/ and *.egg-info beside
the sources). pip needs the package index (or its cache) for setuptools and
flowloop's dependencies; without it this is skipped with the reason.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from devtools import stack
from flowloop.host import install

PROJECT = stack.PROJECT

# folder -> the files a host loads from it; the wheel must carry each one
HOST_FILES = {"klippy_extras": "**/*.py", "moonraker_components": "**/*.py",
              "mcu_sensor": "*.[ch]"}
SKIP = shutil.ignore_patterns(".git", ".venv", ".cache", "build", "dist",
                              "*.egg-info", "__pycache__", ".pytest_cache",
                              ".ruff_cache", ".hypothesis")


def _run(cmd, **kw) -> str:
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True,
                          **kw)
    if proc.returncode != 0:
        text = proc.stdout + proc.stderr
        if any(s in text for s in ("No matching distribution", "Could not find a "
                                   "version", "Failed to establish a new connection",
                                   "Temporary failure in name resolution")):
            pytest.skip(f"pip cannot reach the package index: {text[-300:]}")
        raise AssertionError(f"{' '.join(map(str, cmd))} failed:\n{text[-3000:]}")
    return proc.stdout


@pytest.fixture(scope="module")
def dists(tmp_path_factory):
    """(wheel, sdist) built from a copy of the tree."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    shutil.copytree(PROJECT, src, ignore=SKIP, symlinks=True)
    out = root / "dist"
    # the sdist through setuptools' PEP 517 hook (what `python -m build` calls)
    _run([sys.executable, "-c",
          "import sys; from setuptools import build_meta as b; "
          "print(b.build_sdist(sys.argv[1]))", out], cwd=src)
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
          "--disable-pip-version-check", "-w", out, src])
    (wheel,) = out.glob("*.whl")
    (sdist,) = out.glob("*.tar.gz")
    return wheel, sdist


def _installed(dist: Path, venv: Path) -> Path:
    _run([sys.executable, "-m", "venv", venv])
    _run([venv / "bin" / "python", "-m", "pip", "install", "-q",
          "--disable-pip-version-check", "--no-compile", dist])
    out = _run([venv / "bin" / "python", "-c",
                "import flowloop, os; print(os.path.dirname(flowloop.__file__))"],
               cwd=venv)  # not the checkout's flowloop/
    return Path(out.strip())


def _klipper_copy(dest: Path) -> Path:
    if stack.missing_klipper_reason() is None:
        for rel in ("klippy", "src"):
            shutil.copytree(stack.klipper_path() / rel, dest / rel, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__"))
    else:  # its skeleton: what the installer reads
        from flowloop.host import install
        (dest / "klippy" / "extras").mkdir(parents=True)
        (dest / "klippy" / "klippy.py").write_text("")
        (dest / "src").mkdir()
        (dest / "src" / "Makefile").write_text("src-y += sched.c\n")
        (dest / "src" / "Kconfig").write_text(
            f"config WANT_SPI\n    bool\n{install.LIMITED_MENU}\nendmenu\n")
    return dest


@pytest.mark.parametrize("form", ["wheel", "sdist"])
def test_an_installed_release_links_everything_a_checkout_links(dists, form,
                                                                tmp_path):
    dist = dists[0] if form == "wheel" else dists[1]
    package = _installed(dist, tmp_path / "venv")
    assert PROJECT not in package.parents
    bundle = package / "_hosts"
    for folder, pattern in HOST_FILES.items():
        wanted = sorted(p.relative_to(PROJECT / folder)
                        for p in (PROJECT / folder).glob(pattern)
                        if "__pycache__" not in p.parts)
        assert wanted, folder
        for rel in wanted:
            assert (bundle / folder / rel).read_bytes() == (
                PROJECT / folder / rel).read_bytes(), f"{folder}/{rel}"

    klipper = _klipper_copy(tmp_path / "klipper")
    moonraker = tmp_path / "moonraker"  # a checkout's layout
    (moonraker / "moonraker" / "components").mkdir(parents=True)
    (moonraker / "moonraker" / "components" / "klippy_apis.py").write_text("")
    config = tmp_path / "config"
    config.mkdir()
    (config / "moonraker.conf").write_text("[server]\n")
    flowloop = tmp_path / "venv" / "bin" / "flowloop"
    args = ["install", "--klipper", klipper, "--moonraker", moonraker,
            "--config-dir", config]
    out = _run([flowloop, *args], cwd=tmp_path)
    assert "pip install -U klipper-flowloop" in out
    # every module and package a checkout links (flow_sensor/,
    # flow_sensor_simulation/, measure_profile/ too)
    modules = install.klippy_modules(PROJECT)
    assert {"flow_sensor", "flow_sensor_simulation"} <= {m.name for m in modules}
    for module in modules:
        link = klipper / "klippy" / "extras" / module.name
        assert link.resolve() == (bundle / "klippy_extras" / module.name).resolve()
    # the MCU sources stay out of Klipper's checkout: flowloop firmware's copy
    # takes them from the bundle
    assert not any(p.is_symlink() for p in (klipper / "src").iterdir())
    out = _run([flowloop, "firmware", "--klipper", klipper, "--dry-run"],
               cwd=tmp_path)
    assert "would run make in " in out and "EMS22 sensor command" in out
    comp = moonraker / "moonraker" / "components" / "flowloop"
    assert (comp / "__init__.py").is_file()
    assert comp.resolve() == (bundle / "moonraker_components" / "flowloop").resolve()
    # a pip-installed flowloop is no git repository for Moonraker to pull
    assert "update_manager" not in (config / "moonraker.conf").read_text()

    _run([flowloop, *args, "--uninstall"], cwd=tmp_path)
    assert not any(p.is_symlink() for p in (klipper / "klippy" / "extras").iterdir())
    assert not comp.exists()

    # the commands find their templates in the installed package
    for cmd in ("ab-pylons", "measure-part"):
        gcode = tmp_path / f"{cmd}.gcode"
        _run([flowloop, cmd, "-o", gcode], cwd=tmp_path)
        assert gcode.stat().st_size > 1000

    # the live page's files (the component serves them from the package)
    page = PROJECT / "flowloop" / "host" / "page"
    for asset in sorted(page.iterdir()):
        assert (package / "host" / "page" / asset.name).read_bytes() == \
            asset.read_bytes(), asset.name
    out = _run([tmp_path / "venv" / "bin" / "python", "-c",
                "from flowloop.host import live_page; "
                "print(live_page.document().count(b'<script>'))"], cwd=tmp_path)
    assert out.strip() == "2"


def test_the_sdist_carries_the_host_files_and_no_build_leftovers(dists):
    import tarfile
    with tarfile.open(dists[1]) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
    for folder, pattern in HOST_FILES.items():
        for path in (PROJECT / folder).glob(pattern):
            if "__pycache__" not in path.parts:
                assert str(path.relative_to(PROJECT)) in names
    assert "setup.py" in names
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]


def test_an_editable_install_links_the_checkout_itself():
    from flowloop.host import install
    assert install.source_tree() == PROJECT
