"""docs/install.md as a new user follows it: every `sh` block of the page, in
order, in a home laid out as KIAUH lays it out.

The home is a temporary folder passed as HOME: `~/klipper` and `~/moonraker`
are git clones of the user's checkouts (KLIPPER_PATH, default ~/klipper, and
MOONRAKER_PATH, default ~/moonraker; --shared, so nothing is written into
them), `~/klippy-env` and `~/moonraker-env` are fresh virtualenvs, and
`~/printer_data/config` holds a moonraker.conf and a printer.cfg with
flowloop's sections (one in an included CRLF file).

Each block runs with `bash -e` as the page has it, except for what needs the
network or the machine's services, substituted line by line (SUBSTITUTIONS):

- `git clone https://github.com/flowloop/...` clones this checkout instead,
  with its uncommitted changes copied over (the code under test);
- `pip install ...` gets `--no-deps`: the virtualenvs see the packages of
  this project's .venv (numpy, msgspec, ...) through a .pth file, so only the
  build's own setuptools and wheel come from the index pip is configured with
  (a local mirror on CI; without one the test is skipped, loudly), and the
  page's own path argument (its quoting included) is what pip is given;
- `sudo systemctl ...` is skipped: no klipper or moonraker service runs here.

A block the page marks `<!-- docs-test: skip (reason) -->` is not run (an
interactive menuconfig, a flash, a running Moonraker); every other block is.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from devtools import stack
from flowloop.host import install
from tests.unit.test_install import update_manager_view

DOCS = stack.PROJECT / "docs" / "install.md"
SKIP = re.compile(r"<!-- docs-test: skip \((?P<reason>[^)]*)\) -->\n$")
PIP_OFFLINE = "--no-deps -q"
# pip's answer when no index it is configured with has the build's setuptools
NO_INDEX = "Could not find a version that satisfies the requirement setuptools"
MOONRAKER_CONF = "[server]\nhost: 0.0.0.0\nport: 7125\n\n[update_manager]\n"
PRINTER_CFG = ("[include mainsail.cfg]\n[include flowloop/*.cfg]\n\n[printer]\n"
               "kinematics: corexy\n\n[flowloop]\n")
FLOW_CFG = b"[flow_sensor filament]\r\nsensor_type: ems22\r\ncs_pin: PA4\r\n"


def sh_blocks(text: str):
    """(skip reason or None, block text) for each ```sh block, in order."""
    for match in re.finditer(r"^```sh\n(.*?)^```", text, re.S | re.M):
        before = text[:match.start()]
        skip = SKIP.search(before[-300:])
        yield (skip.group("reason") if skip else None), match.group(1)


def substituted(line: str, clone_with_changes: str) -> str:
    """SUBSTITUTIONS: the page's line as run here."""
    if line.startswith("git clone https://github.com/flowloop/"):
        return clone_with_changes
    if re.match(r"\S*/pip install ", line):
        return line.replace(" install ", f" install {PIP_OFFLINE} ", 1)
    if line.startswith("sudo systemctl"):
        return "true  # " + line
    return line


def clone_command(target: str) -> str:
    """Clone this checkout and copy its uncommitted changes over the clone."""
    project = stack.PROJECT
    changed = subprocess.run(
        ["git", "--no-optional-locks", "-C", str(project), "diff", "--name-only",
         "HEAD"], capture_output=True, text=True, check=True).stdout.split()
    changed = [f for f in changed if (project / f).is_file()]
    copy = (f" && (cd {project} && cp --parents {' '.join(changed)} ~/{target})"
            if changed else "")
    return f"git clone -q --shared {project} {target}{copy}"


def make_venv(path: Path) -> None:
    """A virtualenv with pip that also sees this project's .venv packages."""
    subprocess.run([sys.executable, "-m", "venv", str(path)], check=True)
    site = next(Path(sys.prefix).glob("lib/python3*/site-packages"))
    own = next(path.glob("lib/python3*/site-packages"))
    (own / "project-venv.pth").write_text(f"{site}\n")


@pytest.fixture
def kiauh_home(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    moonraker = Path(os.environ.get("MOONRAKER_PATH", "~/moonraker")).expanduser()
    for source, name in ((stack.klipper_path(), "klipper"), (moonraker, "moonraker")):
        if not (source / ".git").exists():
            pytest.skip(f"!!! SKIPPED: no {name} git checkout at {source}")
        subprocess.run(["git", "clone", "-q", "--shared", str(source),
                        str(home / name)], check=True)
    make_venv(home / "klippy-env")
    make_venv(home / "moonraker-env")
    config = home / "printer_data" / "config"
    (config / "flowloop").mkdir(parents=True)
    (config / "moonraker.conf").write_text(MOONRAKER_CONF)
    (config / "printer.cfg").write_text(PRINTER_CFG)
    (config / "mainsail.cfg").write_text("[pause_resume]\n")
    (config / "flowloop" / "sensor.cfg").write_bytes(FLOW_CFG)
    return home


def run_block(home: Path, block: str) -> subprocess.CompletedProcess:
    lines = [substituted(line, clone_command("flowloop"))
             for line in block.splitlines()]
    env = {k: v for k, v in os.environ.items()
           if k not in ("KLIPPER_PATH", "KALICO_PATH", "MOONRAKER_API_KEY",
                        "VIRTUAL_ENV", "PYTHONPATH")}
    env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"))
    return subprocess.run(["bash", "-e", "-c", "\n".join(lines)], cwd=home, env=env,
                          capture_output=True, text=True, timeout=600)


def test_every_shell_block_of_the_install_page_runs_in_a_kiauh_home(kiauh_home):
    home = kiauh_home
    config = home / "printer_data" / "config"
    conf_before = (config / "moonraker.conf").read_bytes()
    cfg_before = {p: p.read_bytes() for p in config.rglob("*.cfg")}
    ran, outputs = 0, []
    for reason, block in sh_blocks(DOCS.read_text()):
        if reason is not None:
            continue
        proc = run_block(home, block)
        outputs.append(proc.stdout)
        if "flowloop doctor" in block:
            # no Moonraker runs here: the doctor fails that check, and only it
            failing = [line for line in proc.stdout.splitlines()
                       if line.startswith("FAIL")]
            assert [line.split(":")[0] for line in failing] == ["FAIL moonraker"], \
                proc.stdout + proc.stderr
            lines = proc.stdout
            assert "ok   klipper: Klipper" in lines
            assert "ok   links: installed" in lines
            assert "ok   klipper updates: valid" in lines, lines
        else:
            if proc.returncode and NO_INDEX in proc.stderr:
                pytest.skip("!!! SKIPPED: pip finds no setuptools to build the"
                            " editable install with (no index reachable)")
            assert proc.returncode == 0, f"{block}\n{proc.stdout}\n{proc.stderr}"
        ran += 1
        if "flowloop install\n" in block and "--uninstall" not in block and ran == 1:
            # after the step by step: Klipper and Moonraker stay updatable
            for tree in (home / "klipper", home / "moonraker"):
                assert update_manager_view(tree) == {
                    "dirty": False, "modified": [], "untracked": []}, tree
            assert (home / "klipper" / "klippy" / "extras" / "flowloop.py"
                    ).resolve() == home / "flowloop" / "klippy_extras" / "flowloop.py"
            assert "\n[flowloop]\n" in (config / "moonraker.conf").read_text()
    assert ran >= 4  # step by step, doctor, an install again, the uninstall
    assert "nothing to do: flowloop is installed" in outputs[2]
    # after the uninstall: no link, moonraker.conf as it was, printer.cfg's
    # flowloop sections (the included file's too) commented out
    assert not (home / "klipper" / "klippy" / "extras" / "flowloop.py").exists()
    assert (config / "moonraker.conf").read_bytes() == conf_before
    from flowloop.host import klipper_config
    parsed = klipper_config.parse_config((config / "printer.cfg").read_text(),
                                         config / "printer.cfg")
    assert parsed.sections() == ["pause_resume", "printer"]
    assert "comment out [flow_sensor filament]" in outputs[-1]
    assert b"\r\n#[flow_sensor filament]\r\n" in (config / "flowloop" / "sensor.cfg"
                                                  ).read_bytes()
    for tree in (home / "klipper", home / "moonraker"):
        assert update_manager_view(tree) == {"dirty": False, "modified": [],
                                             "untracked": []}
    # the next install restores printer.cfg and its include byte for byte
    proc = run_block(home, "~/klippy-env/bin/flowloop install\n")
    assert proc.returncode == 0, proc.stderr
    assert {p: p.read_bytes() for p in cfg_before} == cfg_before
    assert install.BACKUP_SUFFIX in " ".join(p.name for p in config.rglob("*"))


def test_every_shell_block_is_run_or_says_why_not():
    blocks = list(sh_blocks(DOCS.read_text()))
    assert blocks and all(reason is None or reason.strip() for reason, _ in blocks)
    assert sum(reason is None for reason, _ in blocks) >= 4


def test_no_tilde_inside_quotes_on_the_page():
    """The shell expands ~ only outside quotes: '~/flowloop[moonraker]' fails."""
    for _, block in sh_blocks(DOCS.read_text()):
        assert not re.search(r"""["'][^"'\n]*~/""", block), block
