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
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Set, Tuple, Union

from ..control.heater_range import HeaterRange
from ..errors import FlowloopError, option_message  # noqa: F401 (re-exported)

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
                       own: Dict[Path, configparser.RawConfigParser],
                       visiting: Set[Path]) -> None:
    """Parse text from path into parser, following [include] lines.

    own[file] gets each file's own lines too (its includes not followed):
    which file sets an option is what SAVE_CONFIG checks.
    """
    key = path.resolve()
    if key in visiting:
        raise FlowloopError(f"recursive include of config file {path}")
    visiting.add(key)
    own_parser = own.setdefault(key, _new_parser())

    def add(lines: List[str]) -> None:
        for target in (parser, own_parser):
            _add_text(target, "\n".join(lines), str(path))

    pending: List[str] = []
    for line in text.split("\n"):
        line = _strip_comment(line)
        match = configparser.RawConfigParser.SECTCRE.match(line)
        header = match.group("header") if match else None
        if header is None or not header.startswith("include "):
            pending.append(line)
            continue
        add(pending)
        pending = []
        pattern = os.path.join(str(path.parent), header[len("include "):].strip())
        names = sorted(glob.glob(pattern))
        if not names and not glob.has_magic(pattern):
            raise FlowloopError(f"include file {pattern} does not exist")
        for name in names:
            child = Path(name)
            _add_with_includes(parser, _read_text(child), child, own, visiting)
    add(pending)
    visiting.discard(key)


class KlipperConfig:
    """A parsed printer.cfg; options are looked up as klippy would see them."""

    def __init__(self, parser: configparser.RawConfigParser,
                 own: Dict[Path, configparser.RawConfigParser]):
        self._parser = parser
        self._own = own  # per file, main first: the options its own lines set

    @property
    def files(self) -> List[Path]:
        """The files read (resolved), the main file first, in reading order."""
        return list(self._own)

    def included_files_setting(self, section: str, option: str) -> List[Path]:
        """Files other than the main one whose own lines set [section] option.

        SAVE_CONFIG refuses to save such an option (klippy's configfile:
        "conflicts with included value").
        """
        return [path for path in self.files[1:]
                if self._own[path].has_option(section, option)]

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


def parse_config(text: str, path: Union[str, Path] = "printer.cfg") -> KlipperConfig:
    """Parse config text; includes resolve relative to `path`'s folder."""
    path = Path(path)
    regular_text, autosave_text = split_autosave(text.replace("\r\n", "\n"))
    parser = _new_parser()
    own: Dict[Path, configparser.RawConfigParser] = {}
    _add_with_includes(parser, regular_text, path, own, set())
    block = _new_parser()
    _add_text(block, autosave_text, f"{path} (SAVE_CONFIG block)")
    for section in block.sections():
        if not parser.has_section(section):
            parser.add_section(section)
        for option, value in block.items(section):
            # An option still set above the block wins, as in klippy.
            if not parser.has_option(section, option):
                parser.set(section, option, value)
    return KlipperConfig(parser, own)


def read_config(path: Union[str, Path]) -> KlipperConfig:
    path = Path(path)
    return parse_config(_read_text(path), path)


# --- the hotend heater's range, as klippy requires it -------------------------


def heater_range(config: KlipperConfig, source: str, section: str = "extruder"
                 ) -> Optional[HeaterRange]:
    """The range from a printer.cfg; None without the section. Both options
    are required (klippy does not start without them): one missing is
    refused, as klippy refuses it."""
    if not config.has_section(section):
        return None
    min_c = config.getfloat(section, "min_temp")
    max_c = config.getfloat(section, "max_temp", above=min_c)
    return HeaterRange(min_c, max_c, f"{source} [{section}]")


def printer_heater(printer_cfg: Union[str, Path]) -> Optional[HeaterRange]:
    """The [extruder] range of a printer.cfg file, read as klippy reads it
    ([include]s, CRLF); None without [extruder]."""
    return heater_range(read_config(printer_cfg), str(printer_cfg))


def check_part_temp(printer_cfg: Optional[Union[str, Path]], temp_c: float,
                    name: str) -> Optional[str]:
    """A test part's temperature (option `name`) checked against the
    printer.cfg's [extruder] range (refused outside it); a note for the user
    when it could not be checked, else None."""
    if printer_cfg is None:
        return None
    heater = printer_heater(printer_cfg)
    if heater is None:
        return (f"{printer_cfg} has no [extruder]: {name} not checked against"
                f" its min_temp/max_temp")
    heater.check(temp_c, name)
    return None


# --- config errors, as flowloop's klippy sections report them -----------------


def option_error(config, option: str, message: str):
    """The error a Klipper config section raises for one option (config is
    Klipper's ConfigWrapper; only its get_name() and error() are used)."""
    return config.error(option_message(config.get_name(), option, message))


def check_finite(section: str, values: Dict[str, Optional[float]]) -> None:
    """Refuse nan and inf, naming the option: klippy's getfloat lets them
    through its range checks ('nan' is neither below a minimum nor above a
    maximum). None (an option left unset) is fine."""
    for option, value in values.items():
        if value is not None and not math.isfinite(value):
            raise FlowloopError(option_message(section, option,
                                               f"must be a finite number, not {value}"))


def finite_float(config, option: str, *default, **bounds) -> Optional[float]:
    """A float option of a flowloop section: Klipper's getfloat (default and
    bounds as it takes them: minval=, maxval=, above=, below=), then nan and
    inf refused as check_finite words it, as a config error."""
    value = config.getfloat(option, *default, **bounds)
    try:
        check_finite(config.get_name(), {option: value})
    except FlowloopError as e:
        raise config.error(str(e)) from None
    return value


# --- the klippy a section runs in --------------------------------------------

# How far ahead each host's toolhead reads G-code (its toolhead.py
# BUFFER_TIME_HIGH): a cap or a target decided now acts about that much later
HOST_BUFFER_TIME_S = {"Klipper": 1.0, "Kalico": 2.0}


def host_facts(kalico: bool, heater_control: Optional[str]) -> dict:
    """What flowloop's timing and heating depend on, for the status 'host':
    the host's name, its read-ahead and the heater's control (`pid`,
    `watermark`, Kalico's `mpc`...)."""
    name = "Kalico" if kalico else "Klipper"
    return {"name": name, "buffer_time_s": HOST_BUFFER_TIME_S[name],
            "heater_control": heater_control}


# --- what flowloop's sections look up in klippy ------------------------------
# (printer is klippy's Printer, handed in: this module imports no Klipper)


def find_extruder(printer, name: str):
    """The extruder klippy holds as `name` ([extruder], [extruder1], ...);
    None if no object by that name is one (has no get_heater)."""
    extruder = printer.lookup_object(name, None)
    if extruder is None or not hasattr(extruder, 'get_heater'):
        return None
    return extruder


def extruder_for(printer, section: str, name: str):
    """The extruder a section's `extruder` option names; the config error
    (option_message's format) if it names none. For klippy:connect."""
    extruder = find_extruder(printer, name)
    if extruder is None:
        raise printer.config_error(option_message(
            section, 'extruder', f"'{name}' is not an extruder"))
    return extruder


def section_extruder(section: str, default: str = "extruder") -> str:
    """The extruder a per-tool section acts on, from its name as Klipper's
    `[tmc2209 extruder1]` does: `[autotemp extruder1]` -> extruder1; the
    plain `[autotemp]` -> default (its `extruder` option)."""
    parts = section.split(None, 1)
    return parts[1].strip() if len(parts) == 2 else default


# The simulated sensor of demos and tests: a section of its own, which a real
# printer never has, known to every other section and client as the flow
# sensor [flow_sensor NAME] (docs/flow_sensor.md)
SIMULATION_SECTION = "flow_sensor_simulation"


def simulated_sensor_moved(section: str) -> str:
    """Why [flow_sensor NAME] with sensor_type: simulated is refused."""
    name = section.split()[-1]
    return (f"'simulated' is not a sensor type: the simulated sensor is its own"
            f" section, [{SIMULATION_SECTION} {name}] (the same options without"
            f" sensor_type; docs/flow_sensor.md)")


def flow_sensors(printer) -> list:
    """The object of every [flow_sensor NAME] section, in klippy's order (a
    [flow_sensor_simulation NAME] is one by that name too)."""
    return [obj for name, obj in printer.lookup_objects('flow_sensor')
            if name.startswith('flow_sensor ')]


def find_flow_sensor(printer, extruder_name: str,
                     sensor_name: Optional[str] = None):
    """[flow_sensor sensor_name] if a name is given, else the first flow
    sensor on extruder_name; None if there is none."""
    for sensor in flow_sensors(printer):
        if sensor_name is not None:
            if sensor.name == sensor_name:
                return sensor
        elif sensor.extruder_name == extruder_name:
            return sensor
    return None


# --- which file sets an option ----------------------------------------------


def save_plan(main_config: str, items: Sequence[Tuple[str, str, str]]
              ) -> Tuple[List[Tuple[str, str, str]], List[str]]:
    """Split (section, option, value) items for SAVE_CONFIG.

    Returns the items SAVE_CONFIG can store, and the lines telling the user
    what to paste by hand for the others: SAVE_CONFIG refuses to save an
    option that an included file sets.
    """
    config = read_config(main_config)
    stageable: List[Tuple[str, str, str]] = []
    by_file: Dict[str, List[Tuple[str, str, str]]] = {}
    for item in items:
        files = config.included_files_setting(item[0], item[1])
        if files:
            by_file.setdefault(", ".join(map(str, files)), []).append(item)
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


def save_report(staged: Sequence[Tuple[str, str, str]], paste: Sequence[str]
                ) -> List[str]:
    """What a calibration says after staging values (save_plan's two parts):
    the lines to paste by hand, then what SAVE_CONFIG will store."""
    lines = list(paste)
    if staged:
        names = ", ".join(f"[{section}] {option}" for section, option, _ in staged)
        lines.append(f"Run SAVE_CONFIG to store {names} (Klipper restarts).")
    return lines
