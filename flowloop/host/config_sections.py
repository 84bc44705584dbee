"""flowloop's sections in a printer.cfg: commented out when flowloop is
uninstalled (klippy refuses a section no module provides), restored by the
next install.

Each section goes into a marked block, every line of it behind one '#':

    # >>> flowloop:uninstalled: ... >>>
    #[flow_sensor filament]
    #cs_pin: PA4
    # <<< flowloop:uninstalled <<<

Restoring takes the '#' and the marker lines away again, so the file is
byte for byte what it was. Line endings are the file's own (a CRLF file stays
CRLF). In the SAVE_CONFIG block at the end of printer.cfg every line keeps
its `#*# ` prefix (klippy ignores a block with any other line): the '#' goes
after it. Files are found as klippy finds them: [include] patterns are
globs relative to the including file.
"""

from __future__ import annotations

import glob
import os
import re
from pathlib import Path
from typing import Iterable, List, Sequence, Tuple

BEGIN = ("# >>> flowloop:uninstalled: flowloop install --uninstall commented out"
         " this section; flowloop install restores it >>>")
BEGIN_NEWLINE_ADDED = BEGIN[:-4] + " (newline added) >>>"
END = "# <<< flowloop:uninstalled <<<"
AUTOSAVE_START = "#*# <---------------------- SAVE_CONFIG"
AUTOSAVE_PREFIX = "#*#"
_HEADER = re.compile(r"\[([^\]]+)\]")
_INCLUDE = re.compile(r"\[include\s+([^\]]+)\]")


def _newline(line: str, default: str) -> str:
    stripped = line.rstrip("\r\n")
    return line[len(stripped):] or default


def _split(line: str, autosave: bool) -> Tuple[str, str]:
    """(the SAVE_CONFIG prefix, the config line after it)."""
    if not autosave or not line.startswith(AUTOSAVE_PREFIX):
        return "", line
    cut = 4 if line.startswith(AUTOSAVE_PREFIX + " ") else 3
    return line[:cut], line[cut:]


def _section(line: str, autosave: bool) -> str:
    """The section a header line opens ("flow_sensor x"), else ''."""
    match = _HEADER.match(_split(line, autosave)[1])
    return match.group(1).strip() if match else ""


def _regions(text: str) -> List[Tuple[List[str], bool]]:
    """The lines above the SAVE_CONFIG block, and the block's."""
    lines = text.splitlines(keepends=True)
    start = next((i for i, line in enumerate(lines)
                  if line.startswith(AUTOSAVE_START)), len(lines))
    return [(lines[:start], False), (lines[start:], True)]


def disable(text: str, names: Iterable[str]) -> Tuple[str, List[str]]:
    """Comment out every section whose first word is one of names; returns
    the new text and the sections ("[flow_sensor x]") commented out."""
    names = set(names)
    newline = "\r\n" if "\r\n" in text else "\n"  # for a last line without one
    out: List[str] = []
    found: List[str] = []
    for lines, autosave in _regions(text):
        i = 0
        while i < len(lines):
            section = _section(lines[i], autosave)
            if not section or section.split()[0] not in names:
                out.append(lines[i])
                i += 1
                continue
            end = i + 1
            while end < len(lines) and not _section(lines[end], autosave):
                end += 1
            while end - 1 > i and not _split(lines[end - 1], autosave)[1].strip(
                    "\r\n \t"):
                end -= 1  # blank lines after the section stay as they are
            out += _commented(lines[i:end], autosave, newline)
            found.append(f"[{section}]")
            i = end
    return "".join(out), found


def _commented(lines: Sequence[str], autosave: bool, default: str) -> List[str]:
    prefix = _split(lines[0], autosave)[0]
    newline = _newline(lines[0], default)
    lines = list(lines)
    added = not lines[-1].endswith(("\n", "\r"))
    if added:
        lines[-1] += newline
    out = [prefix + (BEGIN_NEWLINE_ADDED if added else BEGIN) + newline]
    for line in lines:
        pre, rest = _split(line, autosave)
        out.append(pre + "#" + rest)
    out.append(prefix + END + newline)
    return out


def restore(text: str) -> Tuple[str, List[str]]:
    """Undo disable(): the new text and the sections restored."""
    out: List[str] = []
    found: List[str] = []
    for lines, autosave in _regions(text):
        i = 0
        while i < len(lines):
            pre, rest = _split(lines[i], autosave)
            if not rest.startswith((BEGIN, BEGIN_NEWLINE_ADDED)):
                out.append(lines[i])
                i += 1
                continue
            end = i + 1
            while end < len(lines) and not _split(lines[end], autosave)[1].startswith(
                    END):
                end += 1
            if end == len(lines):  # not closed: edited by hand, left alone
                out += lines[i:]
                break
            body = [_uncommented(line, autosave) for line in lines[i + 1:end]]
            if rest.startswith(BEGIN_NEWLINE_ADDED) and body:
                body[-1] = body[-1].rstrip("\r\n")
            if body:
                found.append(f"[{_section(body[0], autosave)}]")
            out += body
            i = end + 1
    return "".join(out), found


def _uncommented(line: str, autosave: bool) -> str:
    pre, rest = _split(line, autosave)
    return pre + rest[1:] if rest.startswith("#") else line


def config_files(printer_cfg: Path) -> List[Path]:
    """printer.cfg and every file it includes (recursively), as klippy reads
    them: each [include] pattern a glob relative to the including file."""
    seen: List[Path] = []

    def visit(path: Path) -> None:
        if path.resolve() in [p.resolve() for p in seen]:
            return
        seen.append(path)
        try:
            text = path.read_bytes().decode("utf-8", errors="replace")
        except OSError:
            return
        for line in _regions(text)[0][0]:
            match = _INCLUDE.match(line)
            if match is None:
                continue
            pattern = os.path.join(str(path.parent), match.group(1).strip())
            for name in sorted(glob.glob(pattern)):
                if os.path.isfile(name):
                    visit(Path(name))
    visit(Path(printer_cfg))
    return seen
