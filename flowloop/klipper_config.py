"""Read a Klipper printer.cfg the way klippy does, without klippy.

- '#' starts a comment anywhere on a line, ';' after whitespace too.
- Repeated sections merge and a later option replaces an earlier one.
- `[include pattern]` reads the matching files (glob, relative to the file that
  includes them, sorted) at that point; a missing plain file is an error.
- The SAVE_CONFIG block at the end (after the `#*# <--- SAVE_CONFIG --->`
  header, every line prefixed `#*# `) is read last. As in klippy, an option
  the block sets is used unless the same option is still set (uncommented)
  above the block: SAVE_CONFIG comments those out when it writes the block,
  so in a file it wrote the block's values are the ones in force.
- A block that was edited by hand (a line without the `#*# ` prefix after the
  header, or a second header) is ignored, as klippy ignores it.
"""

from __future__ import annotations

import configparser
import glob
import math
import os
import re
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Set, Tuple, Union

from .errors import FlowloopError

AUTOSAVE_HEADER = (
    "\n#*# <---------------------- SAVE_CONFIG ---------------------->\n"
    "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n"
    "#*#\n")
AUTOSAVE_PREFIX = "#*# "

_MISSING = object()


def _new_parser() -> configparser.RawConfigParser:
    return configparser.RawConfigParser(strict=False,
                                        inline_comment_prefixes=(";", "#"))


def _strip_comment(line: str) -> str:
    pos = line.find("#")
    return line if pos < 0 else line[:pos]


def split_autosave(text: str) -> Tuple[str, str]:
    """(text above the SAVE_CONFIG block, the block's config without prefixes).

    A hand-edited block gives ("the whole text", ""), as in klippy.
    """
    pos = text.find(AUTOSAVE_HEADER)
    if pos < 0:
        return text, ""
    regular, block = text[:pos], text[pos + len(AUTOSAVE_HEADER):].strip()
    if "\n" + AUTOSAVE_PREFIX in regular or AUTOSAVE_HEADER in block:
        return text, ""
    lines = []
    for line in block.split("\n"):
        if not line.startswith("#*#") or (len(line) > 3
                                          and not line.startswith(AUTOSAVE_PREFIX)):
            return text, ""
        lines.append(line[len(AUTOSAVE_PREFIX):])
    return regular, "\n".join(lines)


def _read_text(path: Path) -> str:
    try:
        return path.read_text().replace("\r\n", "\n")
    except OSError as e:
        raise FlowloopError(f"cannot read config file {path}: {e.strerror}") from None


def _add_text(parser: configparser.RawConfigParser, text: str, source: str) -> None:
    lines = [_strip_comment(line) for line in text.split("\n")]
    try:
        parser.read_string("\n".join(lines), source)
    except configparser.Error as e:
        first = str(e).strip().splitlines()[0]
        raise FlowloopError(f"{source}: {first}") from None


def _add_with_includes(parser: configparser.RawConfigParser, text: str, path: Path,
                       visiting: Set[Path]) -> List[Path]:
    """Parse text from path, following [include] lines; return files read."""
    key = path.resolve()
    if key in visiting:
        raise FlowloopError(f"recursive include of config file {path}")
    visiting.add(key)
    read = [path]
    pending: List[str] = []
    for line in text.split("\n"):
        line = _strip_comment(line)
        match = configparser.RawConfigParser.SECTCRE.match(line)
        header = match.group("header") if match else None
        if header is None or not header.startswith("include "):
            pending.append(line)
            continue
        _add_text(parser, "\n".join(pending), str(path))
        pending = []
        pattern = os.path.join(str(path.parent), header[len("include "):].strip())
        names = sorted(glob.glob(pattern))
        if not names and not glob.has_magic(pattern):
            raise FlowloopError(f"include file {pattern} does not exist")
        for name in names:
            child = Path(name)
            read += _add_with_includes(parser, _read_text(child), child, visiting)
    _add_text(parser, "\n".join(pending), str(path))
    visiting.discard(key)
    return read


class KlipperConfig:
    """A parsed printer.cfg; options are looked up as klippy would see them."""

    def __init__(self, parser: configparser.RawConfigParser,
                 autosave: configparser.RawConfigParser, files: List[Path]):
        self._parser = parser
        self.autosave = autosave
        self.files = files

    # --- lookup -------------------------------------------------------------

    def sections(self) -> List[str]:
        return self._parser.sections()

    def has_section(self, section: str) -> bool:
        return self._parser.has_section(section)

    def has_option(self, section: str, option: str) -> bool:
        return self._parser.has_option(section, option)

    def options(self, section: str) -> Dict[str, str]:
        if not self._parser.has_section(section):
            return {}
        return dict(self._parser.items(section))

    def get(self, section: str, option: str, default: object = _MISSING) -> str:
        if not self._parser.has_option(section, option):
            if default is _MISSING:
                raise FlowloopError(f"Option '{option}' in section '{section}'"
                                    " must be specified")
            return default  # type: ignore[return-value]
        return self._parser.get(section, option)

    def getfloat(self, section: str, option: str, default: object = _MISSING,
                 above: Optional[float] = None) -> float:
        raw = self.get(section, option, default)
        if raw is default and default is not _MISSING:
            return raw  # type: ignore[return-value]
        try:
            value = float(raw)
        except (TypeError, ValueError):
            raise FlowloopError(f"Unable to parse option '{option}' in section"
                                f" '{section}': {raw!r}") from None
        if not math.isfinite(value):
            raise FlowloopError(f"Option '{option}' in section '{section}'"
                                f" must be a finite number, got {raw!r}")
        if above is not None and value <= above:
            raise FlowloopError(f"Option '{option}' in section '{section}'"
                                f" must be above {above}")
        return value

    def from_autosave(self, section: str, option: str) -> bool:
        """True when the value in force came from the SAVE_CONFIG block."""
        return self.autosave.has_option(section, option)


def parse_config(text: str, path: Union[str, Path] = "printer.cfg") -> KlipperConfig:
    """Parse config text; includes resolve relative to `path`'s folder."""
    path = Path(path)
    regular_text, autosave_text = split_autosave(text.replace("\r\n", "\n"))
    parser = _new_parser()
    files = _add_with_includes(parser, regular_text, path, set())
    # An option still set above the block wins, as in klippy.
    kept = []
    section = None
    dropping = False
    for line in autosave_text.split("\n"):
        code = _strip_comment(line).rstrip()
        if code and code[0].isspace():  # continuation of the option above
            if not dropping:
                kept.append(line)
            continue
        dropping = False
        header = configparser.RawConfigParser.SECTCRE.match(code)
        if header:
            section = header.group("header").strip()
        elif code and section is not None:
            option = re.split(r"[=:]", code, maxsplit=1)[0].strip().lower()
            dropping = parser.has_option(section, option)
        if not dropping:
            kept.append(line)
    autosave = _new_parser()
    _add_text(autosave, "\n".join(kept), f"{path} (SAVE_CONFIG block)")
    _add_text(parser, "\n".join(kept), f"{path} (SAVE_CONFIG block)")
    return KlipperConfig(parser, autosave, files)


def read_config(path: Union[str, Path]) -> KlipperConfig:
    path = Path(path)
    return parse_config(_read_text(path), path)


# --- which file sets an option ----------------------------------------------

_SECTION_RE = re.compile(r"^\[(?P<header>[^]]+)\]")
_OPTION_RE = re.compile(r"^(?P<option>[^:=\s][^:=]*?)\s*[:=]")


def included_definitions(main_config: str, section: str, option: str) -> List[str]:
    """Files other than the main config that set [section] option.

    SAVE_CONFIG refuses to save an option that an included file sets, so such
    a value must be pasted into that file by hand.
    """
    main = Path(main_config).resolve()
    files = []
    for path in read_config(main).files:
        path = path.resolve()
        if path != main and path not in files and _file_sets(path, section, option):
            files.append(path)
    return [str(f) for f in files]


def _file_sets(path: Path, section: str, option: str) -> bool:
    """Does this one file (its includes not followed) set the option?"""
    current = None
    for raw in path.read_text(errors="replace").split("\n"):
        line = raw.split("#", 1)[0].rstrip()
        if not line:
            continue
        header = _SECTION_RE.match(line)
        if header:
            current = header.group("header").strip()
            continue
        if current != section or line[0].isspace():
            continue
        match = _OPTION_RE.match(line)
        if match and match.group("option").strip().lower() == option.lower():
            return True
    return False


def save_plan(main_config: str, items: Sequence[Tuple[str, str, str]]
              ) -> Tuple[List[Tuple[str, str, str]], List[str]]:
    """Split (section, option, value) items for SAVE_CONFIG.

    Returns the items SAVE_CONFIG can store, and the lines telling the user
    what to paste by hand for the others: SAVE_CONFIG refuses to save an
    option that an included file sets.
    """
    stageable: List[Tuple[str, str, str]] = []
    by_file: Dict[str, List[Tuple[str, str, str]]] = {}
    for item in items:
        files = included_definitions(main_config, item[0], item[1])
        if files:
            by_file.setdefault(", ".join(files), []).append(item)
        else:
            stageable.append(item)
    lines = []
    for files, pasted in by_file.items():
        lines.append(f"{files} sets these, which SAVE_CONFIG cannot change;"
                     " paste them there:")
        section = None
        for item_section, option, value in pasted:
            if item_section != section:
                section = item_section
                lines.append(f"  [{section}]")
            lines.append(f"  {option}: {value}")
    return stageable, lines
