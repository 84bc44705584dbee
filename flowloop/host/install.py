"""Install flowloop into a user's Klipper and Moonraker, and take it out again.

Everything is planned first and checked (paths exist, trees are what they
claim to be, files are writable, nobody else's file is in the way); only a
plan that passes every check is applied, and a step that still fails rolls
back the steps before it. Text files get marked blocks that --uninstall
removes exactly, so an install followed by an uninstall leaves every file
byte for byte as it was.

The klippy tier of the tests patches its cached Klipper copy with this same
code (plan_klipper + apply), so what the tests run is what users get.
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import time
from pathlib import Path
from typing import Callable, List, Optional, Sequence

from .. import files
from ..errors import FlowloopError
from . import config_sections
from .info import PANEL_URL, PANEL_WEBCAM

PROJECT_URL = "https://github.com/flowloop/klipper-flowloop"
SENSOR_C = "sensor_ems22.c"
LIMITED_MENU = 'menu "Optional features (to reduce code size)"'

# Kconfig: the hidden symbol (default y wherever SPI exists) sits with Klipper's
# other hidden WANT_ options; the prompt sits inside the limited-code-size menu
# (shown only on small-flash MCUs), beside Klipper's own sensor chips.
KCONFIG_HIDDEN = """\
config WANT_SENSOR_EMS22
    bool
    depends on WANT_SPI
    default y
config NEED_SENSOR_BULK
    bool
    depends on WANT_SENSOR_EMS22
    default y
"""
# In that menu the prompt goes with Klipper's own sensor chips ("Other
# external sensor chips"), just before this line.
KCONFIG_PROMPT_BEFORE = 'comment "Other features"'
KCONFIG_PROMPT = """\
config WANT_SENSOR_EMS22
    bool "Support EMS22 filament flow sensor (flowloop)"
    depends on WANT_SPI
"""
MAKEFILE_LINES = "src-$(CONFIG_WANT_SENSOR_EMS22) += sensor_ems22.c\n"

# Kalico: the MCU code is a firmware extra, a folder in src/extras/ with its
# own Kconfig and Makefile; Kalico's scripts/find-firmware-extras.sh sources
# them (its "Firmware Extras" menu) at every make. The folder is flowloop's:
# these two files are written, the sources linked, --uninstall removes it.
KALICO_EXTRA = "flowloop"
KALICO_KCONFIG = """\
# Written by flowloop install; flowloop install --uninstall removes it.
config WANT_SENSOR_EMS22
    bool "Support EMS22 filament flow sensor (flowloop)"
    depends on WANT_SPI
    default y
config NEED_SENSOR_BULK
    bool
    depends on WANT_SENSOR_EMS22
    default y
"""
KALICO_MAKEFILE = f"""\
# Written by flowloop install; flowloop install --uninstall removes it.
dirs-y += src/extras/{KALICO_EXTRA}
src-$(CONFIG_WANT_SENSOR_EMS22) += extras/{KALICO_EXTRA}/{SENSOR_C}
"""

# The oldest Klipper flowloop runs on: klippy_extras need
# mcu.register_serial_response (Klipper commit c89393cda, 2026-02-26). No
# release has it yet: v0.13.0 (2025-04) and older are refused at install.
MIN_KLIPPER = "Klipper from 2026-02-26 on (commit c89393cda)"
MIN_KLIPPER_MARKER = ("klippy/mcu.py", "def register_serial_response(")


def klipper_too_old_message(where: str) -> str:
    return (f"{where} is older than flowloop needs: it lacks"
            f" mcu.register_serial_response; flowloop needs {MIN_KLIPPER}, and"
            " the v0.13.0 release and older are not supported. Update Klipper"
            " (cd ~/klipper; git pull), then run flowloop install again")


class InstallError(FlowloopError):
    pass


# ---------------------------------------------------------------------------
# Marked blocks in text files


def _markers(block_id: str, newline_added: bool = False) -> tuple[str, str]:
    extra = " (newline added)" if newline_added else ""
    return (f"# >>> flowloop:{block_id}{extra} >>>\n",
            f"# <<< flowloop:{block_id} <<<\n")


def find_block(text: str, block_id: str) -> Optional[tuple[int, int, str, bool]]:
    """Return (start, end, body, newline_added); start includes an added newline."""
    for newline_added in (False, True):
        begin, end = _markers(block_id, newline_added)
        i = text.find(begin)
        if i < 0:
            continue
        j = text.find(end, i + len(begin))
        if j < 0:
            raise InstallError(f"flowloop:{block_id} block is not closed")
        start = i - 1 if newline_added and i > 0 and text[i - 1] == "\n" else i
        return start, j + len(end), text[i + len(begin):j], newline_added
    return None


def put_block(text: str, block_id: str, body: str,
              where: Optional[Callable[[str], int]] = None) -> str:
    """Insert (or refresh) a marked block; where(text) gives the offset, else append."""
    found = find_block(text, block_id)
    if found is not None:
        start, stop, old_body, newline_added = found
        if old_body == body:
            return text
        # Refresh in place (an older flowloop's block), keeping how it was joined.
        return text[:start] + _block(block_id, body, newline_added) + text[stop:]
    if where is None:
        newline_added = bool(text) and not text.endswith("\n")
        return text + _block(block_id, body, newline_added)
    pos = where(text)
    return text[:pos] + _block(block_id, body, False) + text[pos:]


def _block(block_id: str, body: str, newline_added: bool) -> str:
    begin, end = _markers(block_id, newline_added)
    return ("\n" if newline_added else "") + begin + body + end


def drop_block(text: str, block_id: str) -> str:
    found = find_block(text, block_id)
    if found is None:
        return text
    start, stop = found[:2]
    return text[:start] + text[stop:]


def _stale_links(changes: List[Change], folder: Path, source: Path,
                 current: Sequence[Path]) -> None:
    """Links into the flowloop checkout that no current file backs (modules an
    older flowloop had): removed by install and uninstall alike."""
    if not folder.is_dir():
        return
    for path in sorted(folder.iterdir()):
        if not path.is_symlink() or path.name in {p.name for p in current}:
            continue
        target = os.readlink(path)
        if Path(target).is_absolute() and source in Path(target).parents:
            changes.append(Change(path, f"remove stale link {path}",
                                  unlink_from=target))


def _line_offset(text: str, line: str, path: Path, after: int = 0) -> int:
    for offset in _line_starts(text, after):
        if text.startswith(line, offset):
            return offset
    raise InstallError(f"{path}: no line '{line}'; is this a Klipper tree of a "
                       f"supported version?")


def _line_starts(text: str, after: int):
    offset = text.rfind("\n", 0, after) + 1 if after else 0
    while offset < len(text):
        yield offset
        nl = text.find("\n", offset)
        if nl < 0:
            return
        offset = nl + 1


# ---------------------------------------------------------------------------
# Changes: planned, checked, then applied with rollback


@dataclasses.dataclass
class Change:
    path: Path
    what: str      # the change as the user reads it, path included: "link A -> B"
    new_text: Optional[str] = None      # write this text
    old_text: Optional[str] = None      # what it replaces (None: a new file)
    link_to: Optional[Path] = None      # create this symlink
    unlink_from: Optional[str] = None   # remove the symlink, which points here
    folder: Optional[str] = None        # "make" or "remove" this (empty) folder
    note: bool = False                  # nothing to do: only `what` is said

    def apply(self) -> None:
        if self.note:
            return
        if self.folder == "make":
            os.mkdir(self.path)
        elif self.folder == "remove":
            os.rmdir(self.path)
        elif self.link_to is not None:
            os.symlink(self.link_to, self.path)
        elif self.unlink_from is not None:
            os.unlink(self.path)
        elif self.new_text is None:
            os.unlink(self.path)  # a file flowloop wrote: removed
        else:
            _write_atomic(self.path, self.new_text)

    def revert(self) -> None:
        if self.note:
            return
        if self.folder == "make":
            os.rmdir(self.path)
        elif self.folder == "remove":
            os.mkdir(self.path)
        elif self.link_to is not None or (self.new_text is not None
                                          and self.old_text is None):
            os.unlink(self.path)  # it did not exist before
        elif self.unlink_from is not None:
            os.symlink(self.unlink_from, self.path)
        else:
            _write_atomic(self.path, self.old_text)

    def check(self, made: Sequence[Path] = ()) -> None:
        """made: folders an earlier change of the same plan creates."""
        if self.note:
            return
        parent = self.path.parent
        while parent in made:
            parent = parent.parent
        if not parent.is_dir():
            raise InstallError(f"{parent}: no such directory")
        if not os.access(parent, os.W_OK):
            raise InstallError(f"{parent}: not writable")
        if self.new_text is not None and self.path.exists() and not os.access(
                self.path, os.W_OK):
            raise InstallError(f"{self.path}: not writable")


def _write_atomic(path: Path, text: str) -> None:
    files.write_text_atomically(path, text)


def check_all(changes: Sequence[Change]) -> None:
    made: List[Path] = []
    for change in changes:
        change.check(made)
        if change.folder == "make":
            made.append(change.path)


def apply(changes: Sequence[Change]) -> None:
    check_all(changes)
    done: List[Change] = []
    try:
        for change in changes:
            change.apply()
            done.append(change)
    except OSError as e:
        for change in reversed(done):
            change.revert()
        raise InstallError(f"{e.filename or ''}: {e.strerror}; nothing was changed"
                           ) from None


def _edit(changes: List[Change], path: Path, what: str,
          edit: Callable[[str], str]) -> None:
    old = read_text(path)
    new = edit(old)
    if new != old:
        changes.append(Change(path, what, new_text=new, old_text=old))


def read_text(path: Path) -> str:
    """A config file's text with its line endings as they are (CRLF kept)."""
    return path.read_bytes().decode("utf-8")


def _link(changes: List[Change], path: Path, target: Path, uninstall: bool) -> None:
    present = path.is_symlink() or path.exists()
    ours = path.is_symlink() and Path(os.readlink(path)) == target
    if present and not ours:
        if uninstall:
            return  # not ours: leave it alone
        raise InstallError(f"{path} exists and is not flowloop's link to {target}; "
                           f"move it away first")
    if uninstall and ours:
        changes.append(Change(path, f"remove link {path}", unlink_from=str(target)))
    elif not uninstall and not ours:
        changes.append(Change(path, f"link {path} -> {target}", link_to=target))


# ---------------------------------------------------------------------------
# What goes where


# Where a built wheel carries what the installer links (setup.py's build_py
# copies klippy_extras/, moonraker_components/ and mcu_sensor/ there).
BUNDLE = "_hosts"


def source_tree() -> Path:
    """What the installer links: the git checkout this package runs from (an
    editable install), else the copy a wheel or sdist install carries."""
    package = Path(__file__).resolve().parents[1]
    root = package.parent
    if (root / "klippy_extras").is_dir():
        return root
    bundle = package / BUNDLE
    if (bundle / "klippy_extras").is_dir():
        return bundle
    raise InstallError(f"{package} has no klippy_extras/ beside or inside it: "
                       f"reinstall flowloop (pip install klipper-flowloop, or "
                       f"pip install -e from a git checkout)")


def is_checkout(source: Path) -> bool:
    """A git checkout (Moonraker's update_manager can pull it), not a wheel."""
    return (source / ".git").exists()


def _modules(folder: Path) -> List[Path]:
    """The modules and packages in a folder: what a host imports by name."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if (p.suffix == ".py" or (p / "__init__.py").is_file())
                  and not p.name.startswith(("_", ".")))


def klippy_modules(source: Path) -> List[Path]:
    return _modules(source / "klippy_extras")


def moonraker_components(source: Path) -> List[Path]:
    """Moonraker components: a module, or a package like Moonraker's own
    update_manager/; each is linked whole into moonraker/components/."""
    return _modules(source / "moonraker_components")


def mcu_sources(source: Path) -> List[Path]:
    sensor = source / "mcu_sensor"
    if not (sensor / SENSOR_C).is_file():
        return []
    return sorted(p for p in sensor.iterdir() if p.suffix in (".c", ".h"))


def check_klipper_tree(klipper: Path) -> None:
    for rel in ("klippy/klippy.py", "klippy/extras", "src/Makefile", "src/Kconfig"):
        if not (klipper / rel).exists():
            if not klipper.exists():
                raise InstallError(f"{klipper}: no such directory")
            raise InstallError(f"{klipper} is not a Klipper tree (no {rel})")


def _prompt_offset(text: str, kconfig: Path) -> int:
    """Where the sensor's prompt goes in the limited-code-size menu: with
    Klipper's own sensor chips (before its "Other features" comment), else
    at the menu's end."""
    menu = _line_offset(text, LIMITED_MENU, kconfig)
    try:
        return _line_offset(text, KCONFIG_PROMPT_BEFORE, kconfig, menu)
    except InstallError:
        return _line_offset(text, "endmenu", kconfig, menu)


def check_klipper_version(klipper: Path) -> None:
    """Refuse a Klipper older than MIN_KLIPPER (a feature check: forks and
    untagged checkouts are judged by what they offer)."""
    rel, marker = MIN_KLIPPER_MARKER
    path = klipper / rel
    if path.is_file() and marker not in path.read_text(errors="replace"):
        raise InstallError(klipper_too_old_message(f"Klipper at {klipper}"))


def git_exclude_file(tree: Path) -> Optional[Path]:
    dotgit = tree / ".git"
    if dotgit.is_dir():
        return dotgit / "info" / "exclude"
    if dotgit.is_file():  # a worktree: "gitdir: PATH"; excludes live in the
        gitdir = (tree / dotgit.read_text().partition("gitdir:")[2].strip()).resolve()
        common = gitdir / "commondir"  # main repository's git dir
        if common.is_file():
            gitdir = (gitdir / common.read_text().strip()).resolve()
        return gitdir / "info" / "exclude"
    return None


def _exclude_changes(changes: List[Change], tree: Path, rel_paths: List[str],
                     uninstall: bool) -> None:
    exclude = git_exclude_file(tree)
    if exclude is None:
        return
    body = "".join(f"/{rel}\n" for rel in rel_paths)
    if not exclude.exists():
        if not uninstall and body and exclude.parent.is_dir():
            changes.append(Change(exclude, f"write {exclude}: git ignores"
                                  f" flowloop's links",
                                  new_text=put_block("", "files", body)))
        return
    if uninstall or not body:
        _edit(changes, exclude, f"remove flowloop's links from {exclude}",
              lambda t: drop_block(t, "files"))
    else:
        _edit(changes, exclude, f"add flowloop's links to {exclude} (git ignores"
              f" them)", lambda t: put_block(t, "files", body))


def is_kalico(klipper: Path) -> bool:
    """Kalico (the Klipper fork): klippy loads plugins from klippy/plugins/
    and its Makefile finds firmware extras in src/extras/."""
    return ((klipper / "klippy" / "plugins" / "__init__.py").is_file()
            and (klipper / "scripts" / "find-firmware-extras.sh").is_file())


def host_name(klipper: Path) -> str:
    return "Kalico" if is_kalico(Path(klipper).expanduser()) else "Klipper"


def _own_file(changes: List[Change], path: Path, text: str, uninstall: bool) -> None:
    """A file flowloop writes whole (its first line says so): written,
    refreshed, or removed; anyone else's file of that name is refused."""
    header = text.splitlines(keepends=True)[0]
    if path.is_symlink() or path.exists():
        old = path.read_text(encoding="utf-8") if path.is_file() else ""
        if not old.startswith(header) or path.is_symlink():
            if uninstall:
                return
            raise InstallError(f"{path} exists and is not flowloop's; move it away "
                               f"first")
        if uninstall:
            changes.append(Change(path, f"remove {path}", old_text=old))
        elif old != text:
            changes.append(Change(path, f"refresh {path}", new_text=text,
                                  old_text=old))
    elif not uninstall:
        changes.append(Change(path, f"write {path}", new_text=text))


def plan_kalico(klipper: Path, source: Path, uninstall: bool) -> List[Change]:
    """Kalico's way: klippy modules as plugins, the MCU code as a firmware
    extra; no file of Kalico's is edited (both folders are git-ignored by
    Kalico). Links and blocks a Klipper-style install left are taken out."""
    changes: List[Change] = []
    modules = klippy_modules(source)
    plugins = klipper / "klippy" / "plugins"
    extras = klipper / "klippy" / "extras"
    if not uninstall:
        for module in modules:
            own = extras / module.name
            if own.exists() and not own.is_symlink():
                raise InstallError(
                    f"{own}: Kalico has a module named {module.name} itself; "
                    f"Kalico refuses a plugin of the same name")
    for module in modules:
        _link(changes, plugins / module.name, module, uninstall)
    _stale_links(changes, plugins, source, modules)
    _stale_links(changes, extras, source, [])  # a Klipper-style install
    _stale_links(changes, klipper / "src", source, [])
    _edit(changes, klipper / "src" / "Makefile",
          f"remove the EMS22 sensor source from {klipper / 'src' / 'Makefile'}",
          lambda t: drop_block(t, "sensor"))
    _edit(changes, klipper / "src" / "Kconfig",
          f"remove the EMS22 sensor option from {klipper / 'src' / 'Kconfig'}",
          lambda t: drop_block(drop_block(t, "sensor-prompt"), "sensor"))
    folder = klipper / "src" / "extras" / KALICO_EXTRA
    c_files = mcu_sources(source)
    remove = uninstall or not c_files
    # Kalico's src/extras/.gitignore ignores all it holds; a tree without it
    # (src/extras not made yet) gets the extra listed in .git/info/exclude.
    ignored = (folder.parent / ".gitignore").is_file()
    _exclude_changes(changes, klipper, [f"src/extras/{KALICO_EXTRA}"],
                     uninstall=remove or ignored)
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        if remove:
            return changes
        raise InstallError(f"{folder} exists and is not flowloop's firmware extra;"
                           f" move it away first")
    if not folder.exists():
        if remove:
            return changes
        if not folder.parent.exists():
            changes.append(Change(folder.parent, f"make folder {folder.parent}",
                                  folder="make"))
        changes.append(Change(folder, f"make folder {folder}", folder="make"))
    before = len(changes)
    for c_file in c_files:
        _link(changes, folder / c_file.name, c_file, remove)
    _stale_links(changes, folder, source, c_files)
    _own_file(changes, folder / "Kconfig", KALICO_KCONFIG, remove)
    _own_file(changes, folder / "Makefile", KALICO_MAKEFILE, remove)
    if remove and folder.is_dir():
        gone = {c.path for c in changes[before:]}
        if all(p in gone for p in folder.iterdir()):
            changes.append(Change(folder, f"remove folder {folder}",
                                  folder="remove"))
            if not ignored and list(folder.parent.iterdir()) == [folder]:
                changes.append(Change(folder.parent, "remove folder"
                                      f" {folder.parent}", folder="remove"))
    return changes


def plan_klipper(klipper: Path, source: Path, uninstall: bool = False) -> List[Change]:
    """Klipper's checkout: links in klippy/extras/, listed in .git/info/exclude,
    and no tracked file changed, so Moonraker's update manager sees it
    pristine. The MCU code is built from a copy (flowloop firmware); the
    src/ edits an older flowloop made here are taken out."""
    klipper = Path(klipper).expanduser()
    check_klipper_tree(klipper)
    if is_kalico(klipper):
        return plan_kalico(klipper, source, uninstall)
    if not uninstall:
        check_klipper_version(klipper)
    changes: List[Change] = []
    excluded = []
    for module in klippy_modules(source):
        rel = f"klippy/extras/{module.name}"
        _link(changes, klipper / rel, module, uninstall)
        excluded.append(rel)
    _stale_links(changes, klipper / "klippy" / "extras", source,
                 klippy_modules(source))
    for change in plan_firmware(klipper, source, uninstall=True):
        change.what += OLD_FIRMWARE_EDIT
        changes.append(change)
    _exclude_changes(changes, klipper, excluded, uninstall)
    return changes


# Said of each src/ edit an older flowloop made in the checkout, as it goes.
OLD_FIRMWARE_EDIT = (" (left by an older flowloop; Klipper's checkout keeps no"
                     " flowloop edit now: flowloop firmware builds the sensor)")


def plan_firmware(tree: Path, source: Path, uninstall: bool = False) -> List[Change]:
    """The EMS22 command in a Klipper tree's MCU build: the sources linked
    into src/, one line in src/Makefile, the option in src/Kconfig. Made
    only in a copy make builds from (flowloop firmware's, the tests'), never
    in the user's checkout; Kalico takes it as a firmware extra instead
    (plan_kalico), so there is nothing to do here."""
    tree = Path(tree).expanduser()
    if is_kalico(tree):
        return []
    changes: List[Change] = []
    c_files = mcu_sources(source)
    remove = uninstall or not c_files
    for c_file in c_files:
        _link(changes, tree / "src" / c_file.name, c_file, remove)
    _stale_links(changes, tree / "src", source, c_files)
    makefile = tree / "src" / "Makefile"
    kconfig = tree / "src" / "Kconfig"
    if remove:
        _edit(changes, makefile, f"remove the EMS22 sensor source from {makefile}",
              lambda t: drop_block(t, "sensor"))
        _edit(changes, kconfig, f"remove the EMS22 sensor option from {kconfig}",
              lambda t: drop_block(drop_block(t, "sensor-prompt"), "sensor"))
        return changes
    _edit(changes, makefile, f"add the EMS22 sensor source to {makefile}",
          lambda t: put_block(t, "sensor", MAKEFILE_LINES))

    def kconfig_edit(text: str) -> str:
        text = put_block(text, "sensor", KCONFIG_HIDDEN,
                         lambda t: _line_offset(t, LIMITED_MENU, kconfig))
        return put_block(text, "sensor-prompt", KCONFIG_PROMPT,
                         lambda t: _prompt_offset(t, kconfig))
    _edit(changes, kconfig, f"add the EMS22 sensor option (make menuconfig)"
          f" to {kconfig}", kconfig_edit)
    return changes


def moonraker_components_dir(moonraker: Path) -> Path:
    """Find moonraker/components/ from a venv (ask its python) or a checkout."""
    moonraker = Path(moonraker).expanduser()
    if not moonraker.exists():
        raise InstallError(f"{moonraker}: no such directory")
    checkout = moonraker / "moonraker" / "components"
    if (checkout / "klippy_apis.py").is_file():
        return checkout
    python = moonraker / "bin" / "python"
    if not python.exists():
        raise InstallError(f"{moonraker} is neither a Moonraker checkout nor a "
                           f"virtualenv (no bin/python)")
    proc = subprocess.run(
        [str(python), "-c",
         "import os, moonraker.components as c; print(os.path.dirname(c.__file__))"],
        capture_output=True, text=True)
    if proc.returncode != 0:
        raise InstallError(f"{python} cannot import moonraker; install Moonraker "
                           f"into that virtualenv or pass the Moonraker checkout")
    return Path(proc.stdout.strip())


def plan_moonraker(moonraker: Path, source: Path,
                   uninstall: bool = False) -> List[Change]:
    components = moonraker_components_dir(moonraker)
    changes: List[Change] = []
    comps = moonraker_components(source)
    for comp in comps:
        _link(changes, components / comp.name, comp, uninstall)
    _stale_links(changes, components, source, comps)
    rels = [f"moonraker/components/{comp.name}" for comp in comps]
    checkout = components.parent.parent
    if (checkout / ".git").exists():
        _exclude_changes(changes, checkout, rels, uninstall)
    return changes


def update_manager_block(source: Path) -> str:
    origin = _git_origin(source) or PROJECT_URL
    return (f"[update_manager flowloop]\n"
            f"type: git_repo\n"
            f"path: {source}\n"
            f"origin: {origin}\n"
            f"primary_branch: main\n"
            f"managed_services: klipper moonraker\n")


def _git_origin(source: Path) -> Optional[str]:
    try:
        proc = subprocess.run(["git", "-C", str(source), "remote", "get-url", "origin"],
                              capture_output=True, text=True)
    except OSError:
        return None
    if proc.returncode != 0:
        return None
    return proc.stdout.strip() or None


# A user's own [flowloop] in moonraker.conf (uncommented, at a line's start).
FLOWLOOP_SECTION = re.compile(r"^\[flowloop\][ \t]*(?:[#;].*)?\r?$", re.MULTILINE)
COMPONENT_BLOCK = "\n[flowloop]\n"
# The live page as a panel of Mainsail's and Fluidd's dashboards: a webcam of
# service iframe (read-only in both UIs: it comes from moonraker.conf).
WEBCAM_SECTION = re.compile(rf"^\[webcam[ \t]+{PANEL_WEBCAM}\][ \t]*(?:[#;].*)?\r?$",
                            re.MULTILINE)
WEBCAM_BLOCK = (f"\n[webcam {PANEL_WEBCAM}]\n"
                f"# flowloop's live page in the dashboard (docs/ui.md)\n"
                f"service: iframe\n"
                f"stream_url: {PANEL_URL}\n"
                f"icon: mdiPrinter3dNozzle\n"
                f"aspect_ratio: 4:3\n")
# Backups sit beside the file; not named *.cfg or *.conf, so no [include *.cfg]
# of klippy's or Moonraker's reads one.
BACKUP_SUFFIX = ".flowloop-backup-"


def backup_path(path: Path) -> Path:
    stamp = time.strftime("%Y%m%d_%H%M%S")
    candidate = path.with_name(f"{path.name}{BACKUP_SUFFIX}{stamp}")
    n = 1
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.name}{BACKUP_SUFFIX}{stamp}-{n}")
    return candidate


def _edit_with_backup(changes: List[Change], path: Path, what: str,
                      edit: Callable[[str], str]) -> None:
    """An edit of a user's config file, its old text kept in a backup first."""
    old = read_text(path)
    new = edit(old)
    if new == old:
        return
    backup = backup_path(path)
    changes.append(Change(backup, f"back up {path} to {backup.name}",
                          new_text=old))
    changes.append(Change(path, what, new_text=new, old_text=old))


def _keeping_crlf(edit: Callable[[str], str]) -> Callable[[str], str]:
    """A block edit of a CRLF file writes CRLF too (a mixed file: as it is)."""
    def edited(text: str) -> str:
        if "\r\n" in text and "\n" not in text.replace("\r\n", ""):
            return edit(text.replace("\r\n", "\n")).replace("\n", "\r\n")
        return edit(text)
    return edited


def plan_moonraker_conf(config_dir: Path, source: Path,
                        uninstall: bool = False) -> List[Change]:
    """moonraker.conf: the component's own [flowloop] section, the live page
    as a dashboard panel ([webcam flowloop]) and, for a git checkout,
    [update_manager flowloop]; each a marked block that uninstall takes out
    again. A section of the user's own is left alone."""
    conf = Path(config_dir).expanduser() / "moonraker.conf"
    if not conf.is_file():
        raise InstallError(f"{conf}: no such file (use --config-dir)")
    changes: List[Change] = []
    text = read_text(conf).replace("\r\n", "\n")
    if uninstall:
        _edit_with_backup(changes, conf, f"remove [flowloop], [webcam "
                          f"{PANEL_WEBCAM}] and [update_manager flowloop] from "
                          f"{conf}", _keeping_crlf(lambda t: drop_block(drop_block(
                              drop_block(t, "update-manager"), "webcam"),
                              "component")))
        return changes
    edits: List[Callable[[str], str]] = []
    said: List[str] = []
    for block, section, pattern, body in (
            ("component", "[flowloop]", FLOWLOOP_SECTION, COMPONENT_BLOCK),
            ("webcam", f"[webcam {PANEL_WEBCAM}]", WEBCAM_SECTION, WEBCAM_BLOCK)):
        if pattern.search(drop_block(text, block)):   # the user's own wins
            changes.append(Change(conf, f"{conf} has a {section} section of its "
                                  f"own: left as it is", note=True))
            edits.append(lambda t, block=block: drop_block(t, block))
        else:
            edits.append(lambda t, block=block, body=body: put_block(t, block, body))
            said.append(section)
    if not is_checkout(source):
        # Installed from a wheel: pip updates it, not a git_repo updater.
        edits.append(lambda t: drop_block(t, "update-manager"))
    elif (find_block(text, "update-manager") is not None
          or "[update_manager flowloop]" not in text):  # the user's own wins
        edits.append(lambda t: put_block(t, "update-manager",
                                         "\n" + update_manager_block(source)))
        said.append("[update_manager flowloop]")

    def edit(t: str) -> str:
        for one in edits:
            t = one(t)
        return t
    what = (f"add {' and '.join(said)} to {conf}" if said
            else f"update flowloop's blocks in {conf}")
    _edit_with_backup(changes, conf, what, _keeping_crlf(edit))
    return changes


def klippy_sections(source: Path) -> List[str]:
    """The config sections flowloop's klippy modules provide (one per module,
    named as it is: flow_sensor gives [flow_sensor NAME])."""
    return [m.name[:-3] if m.suffix == ".py" else m.name
            for m in klippy_modules(source)]


def plan_printer_cfg(config_dir: Path, source: Path,
                     uninstall: bool = False) -> List[Change]:
    """printer.cfg and the files it includes: uninstall comments flowloop's
    sections out (klippy refuses a section no module provides), install
    restores what an uninstall commented out."""
    main = Path(config_dir).expanduser() / "printer.cfg"
    if not main.is_file():
        return []
    changes: List[Change] = []
    names = klippy_sections(source)
    for path in config_sections.config_files(main):
        text = read_text(path)
        if uninstall:
            new, found = config_sections.disable(text, names)
        else:
            new, found = config_sections.restore(text)
        if new == text:
            continue
        if Path(source).resolve() in path.resolve().parents:
            changes.append(Change(path, f"{main} includes {path} from flowloop"
                                  f" itself, with {', '.join(found)}: remove that"
                                  f" [include] by hand", note=True))
            continue
        what = (f"comment out {', '.join(found)} in {path} (klippy starts without"
                f" flowloop; flowloop install restores them)" if uninstall else
                f"restore {', '.join(found)} in {path} (commented out by flowloop"
                f" install --uninstall)")
        _edit_with_backup(changes, path, what, lambda t, new=new: new)
    return changes
