"""docs/reference.md names everything the code offers, and nothing it lacks.

The facts come from the code itself: the klippy_extras modules (a module or a
package of them) and the Moonraker component are parsed (ast), following a
G-code command's `gcmd` into every helper it is handed to, and the CLI parser
is built and walked. Status fields are what `get_status` really returns: the
klippy tier (tests/klippy/test_reference_status.py) loads every section in
klippy and checks them, with the options Klipper's configfile saw read. The
page is read as markdown tables under fixed headings, so a name counts only
where a user would look for it (an option in its section's Options table, a
parameter in its command's row).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import re
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Set, Tuple

import pytest

from flowloop import cli

PROJECT = Path(__file__).resolve().parents[2]
DOCS = PROJECT / "docs"
REFERENCE = DOCS / "reference.md"
EXTRAS = PROJECT / "klippy_extras"
COMPONENT = PROJECT / "moonraker_components" / "flowloop"   # a package, or .py
MACROS = PROJECT / "macros"

CONFIG_GETTER = re.compile(r"^get(int|float|boolean|choice|list|lists|intlist|"
                           r"floatlist)?$")
GCMD_GETTER = re.compile(r"^get(_int|_float)?$")
# flowloop's one number reader for G-code (klippy_extras/flowloop.py, and the
# adapters' short names for it), called as reader(gcmd, 'NAME', ...)
GCMD_READERS = ("gcode_number", "gcode_integer", "number", "integer")
COMMAND_NAME = re.compile(r"^[A-Z][A-Z0-9_]*$")
# Klipper helpers that read options of the calling section (klippy/extras/bus.py
# MCU_SPI_from_config, klippy/extras/probe.py ProbePointsHelper).
HELPER_OPTIONS = {
    "MCU_SPI_from_config": ("cs_pin", "spi_speed", "spi_bus", "spi_software_sclk_pin",
                            "spi_software_mosi_pin", "spi_software_miso_pin"),
    "ProbePointsHelper": ("points", "horizontal_move_z", "speed"),
}
# G-code parameters a Klipper helper reads from the command it is handed.
HELPER_PARAMS = {"start_probe": ("METHOD", "HORIZONTAL_MOVE_Z")}
REQUEST_TYPES = ("GET", "POST", "DELETE")   # Moonraker's RequestType flag order


# --- facts from the code --------------------------------------------------------

@dataclasses.dataclass
class Command:
    name: str
    help: str
    params: Set[str]


@dataclasses.dataclass
class KlippySection:
    module: str
    prefix: bool                       # load_config_prefix: [module NAME]
    options: Set[str]
    commands: Dict[str, Command]
    endpoints: Set[str]
    status: Optional[Set[str]] = None  # known only from a running klippy


def _str(node: ast.AST) -> Optional[str]:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    return None


def _called_name(call: ast.Call) -> Optional[str]:
    func = call.func
    if isinstance(func, ast.Attribute):
        return func.attr
    if isinstance(func, ast.Name):
        return func.id
    return None


def _where(path: Path, node: ast.AST) -> str:
    return f"{path.relative_to(PROJECT)}:{node.lineno}"


def config_options(path: Path, tree: ast.AST) -> Set[str]:
    """Options read with config.get*('name', ...) or by a Klipper helper."""
    names: Set[str] = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        called = _called_name(node)
        names.update(HELPER_OPTIONS.get(called or "", ()))
        func = node.func
        if called == "finite_float" and len(node.args) > 1:
            # flowloop's float reader: finite_float(config, 'name', ...)
            names.add(_str(node.args[1]))
        elif (isinstance(func, ast.Name) and func.id == "getfloat"
              and node.args and _str(node.args[0]) is not None):
            # its short name, functools.partial(finite_float, config)
            names.add(_str(node.args[0]))
        elif (isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name)
                and func.value.id == "config" and CONFIG_GETTER.match(func.attr)):
            name = _str(node.args[0]) if node.args else None
            assert name is not None, (
                f"{_where(path, node)}: option name is not a string literal; "
                "the reference test cannot see it")
            names.add(name)
    return names


def _functions(tree: ast.AST) -> Iterator[ast.FunctionDef]:
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef):
            yield node


def _registrations(tree: ast.AST, method: str) -> Iterator[Tuple[ast.Call, list]]:
    """Calls of `method`, each with its argument lists: the call's own, or,
    when its first argument is a variable, every tuple literal of the adapter
    that starts with a string (the `for name, func, desc in table` idiom, the
    table built wherever the adapter builds it)."""
    tables = [list(t.elts) for t in ast.walk(tree)
              if isinstance(t, ast.Tuple) and t.elts and _str(t.elts[0]) is not None]
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and _called_name(node) == method):
            continue
        args = list(node.args)
        if method == "register_endpoint" and len(args) > 1 \
                and _str(args[0]) is None and _str(args[1]) is not None:
            args = args[1:]   # flowloop's helper that takes the server first
        if args and _str(args[0]) is not None:
            yield node, [args]
        else:
            yield node, tables


def _methods(tree: ast.AST) -> Dict[str, List[ast.FunctionDef]]:
    """Every function and method of the adapter, by name (helpers included)."""
    out: Dict[str, List[ast.FunctionDef]] = {}
    for f in _functions(tree):
        out.setdefault(f.name, []).append(f)
    return out


def _hands_on_gcmd(call: ast.Call) -> bool:
    values = list(call.args) + [k.value for k in call.keywords]
    return any(isinstance(v, ast.Name) and v.id == "gcmd" for v in values)


def _gcmd_params(methods: Dict[str, List[ast.FunctionDef]], name: str,
                 seen: Optional[Set[str]] = None) -> Set[str]:
    """gcmd.get*('NAME') in a handler and in every function it hands gcmd to,
    or calls on self: by name, across all the adapter's classes and files."""
    seen = set() if seen is None else seen
    if name in seen or name not in methods:
        return set()
    seen.add(name)
    params: Set[str] = set()
    for func_def in methods[name]:
        for node in ast.walk(func_def):
            if not isinstance(node, ast.Call):
                continue
            called = _called_name(node)
            params.update(HELPER_PARAMS.get(called or "", ()))
            func = node.func
            if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name) \
                    and func.value.id == "gcmd" and GCMD_GETTER.match(func.attr) \
                    and node.args:
                param = _str(node.args[0])
                if param is not None:      # f-string families (A1..A9) unchecked
                    params.add(param)
            elif called in GCMD_READERS and len(node.args) > 1 \
                    and _hands_on_gcmd(node):
                param = _str(node.args[1])
                if param is not None:
                    params.add(param)
            elif called and (_hands_on_gcmd(node) or (
                    isinstance(func, ast.Attribute)
                    and isinstance(func.value, ast.Name)
                    and func.value.id == "self")):
                params |= _gcmd_params(methods, called, seen)
    return params


def _help_texts(tree: ast.AST) -> Dict[str, str]:
    texts = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and len(node.targets) == 1 \
                and isinstance(node.targets[0], ast.Name) \
                and node.targets[0].id.endswith("_help"):
            texts[node.targets[0].id] = ast.literal_eval(node.value)
    return texts


def gcode_commands(path: Path, tree: ast.AST) -> Dict[str, Command]:
    methods = _methods(tree)
    helps = _help_texts(tree)
    commands: Dict[str, Command] = {}
    for method, handler_index in (("register_command", 1),
                                  ("register_mux_command", 3)):
        for call, rows in _registrations(tree, method):
            mux_key = _str(call.args[1]) if method == "register_mux_command" else None
            direct = _str(call.args[0]) is not None
            for args in rows:
                name = _str(args[0])
                if not COMMAND_NAME.match(name or ""):
                    continue
                handler = args[handler_index if direct else 1] \
                    if len(args) > 1 else None
                if not direct and not isinstance(handler, ast.Attribute):
                    continue          # a table row that is not (name, handler, ...)
                if isinstance(handler, ast.Constant) and handler.value is None:
                    continue          # register_command(name, None): taking one over
                assert isinstance(handler, ast.Attribute), _where(path, call)
                params = _gcmd_params(methods, handler.attr)
                if mux_key:
                    params.add(mux_key)
                help_text = helps.get(handler.attr + "_help")
                assert help_text is not None, f"{name}: no {handler.attr}_help"
                commands[name] = Command(name, help_text, params)
    # Every cmd_X_help belongs to a command found above: nothing registered in
    # a way this parser does not understand slips past it.
    found = {"cmd_" + name + "_help" for name in commands}
    missed = {h for h in helps if h.startswith("cmd_")} - found
    assert not missed, f"{path.name}: commands not understood: {sorted(missed)}"
    return commands


def webhooks_endpoints(tree: ast.AST) -> Set[str]:
    paths = set()
    for method in ("register_endpoint", "register_mux_endpoint", "add_mux_endpoint"):
        for _call, rows in _registrations(tree, method):
            paths.update(_str(args[0]) for args in rows if "/" in _str(args[0]))
    return paths


def adapter_sources() -> Dict[str, List[Path]]:
    """klippy module name -> its files: a module, or a package's modules."""
    out = {}
    for path in sorted(EXTRAS.iterdir()):
        if path.suffix == ".py" and path.name != "__init__.py":
            out[path.stem] = [path]
        elif (path / "__init__.py").is_file():
            out[path.name] = sorted(path.rglob("*.py"))
    return out


def _parse_all(paths: List[Path]) -> ast.Module:
    body: list = []
    for path in paths:
        body += ast.parse(path.read_text(), str(path)).body
    return ast.Module(body=body, type_ignores=[])


def klippy_sections() -> List[KlippySection]:
    sections = []
    for module, paths in adapter_sources().items():
        tree = _parse_all(paths)
        where = paths[0] if len(paths) == 1 else paths[0].parent
        sections.append(KlippySection(
            module=module,
            prefix="load_config_prefix" in _methods(tree),
            options=config_options(where, tree),
            commands=gcode_commands(where, tree),
            endpoints=webhooks_endpoints(tree)))
    return sections


def _request_types(node: ast.AST) -> List[str]:
    names = {n.attr for n in ast.walk(node)
             if isinstance(n, ast.Attribute) and n.attr in REQUEST_TYPES}
    return [t for t in REQUEST_TYPES if t in names]


@dataclasses.dataclass
class Component:
    options: Set[str]
    endpoints: Set[Tuple[str, str, str]]   # (HTTP method, path, JSON-RPC method)
    notifications: Set[str]
    remote_methods: Set[str]


def component_sources() -> List[Path]:
    module = COMPONENT.with_suffix(".py")
    return [module] if module.is_file() else sorted(COMPONENT.rglob("*.py"))


def moonraker_component() -> Component:
    sources = component_sources()
    tree = _parse_all(sources)
    endpoints = set()
    for _call, rows in _registrations(tree, "register_endpoint"):
        for args in rows:
            path = _str(args[0])
            if not path.startswith("/"):
                continue
            types = _request_types(args[1])
            parts = path.strip("/").split("/")
            for rtype in types:
                if len(types) > 1:   # Moonraker's rule for one path, many methods
                    rpc = ".".join(parts[:-1] + [rtype.lower() + "_" + parts[-1]])
                else:
                    rpc = ".".join(parts)
                endpoints.add((rtype, path, rpc))
    # Every /server/ path in the file was found as a registration.
    literals = {_str(n) for n in ast.walk(tree)
                if (_str(n) or "").startswith("/server/")}
    assert literals == {p for _t, p, _r in endpoints}, literals
    notifications = set()
    for call, _rows in _registrations(tree, "register_notification"):
        event = _str(call.args[0])
        name = _str(call.args[1]) if len(call.args) > 1 else event.split(":")[-1]
        notifications.add("notify_" + name)
    remote = {_str(call.args[0])
              for call, _rows in _registrations(tree, "register_remote_method")}
    return Component(config_options(sources[0], tree), endpoints, notifications,
                     remote)


def cli_commands() -> Dict[str, Set[str]]:
    """'profile show' -> its long options; '' is the top-level parser."""
    out: Dict[str, Set[str]] = {}

    def walk(parser: argparse.ArgumentParser, path: str) -> None:
        out[path] = set()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{path} {name}".strip())
            else:
                out[path].update(o for o in action.option_strings
                                 if o.startswith("--") and o != "--help")
    walk(cli.build_parser(), "")
    return out


def macros() -> Dict[str, Set[str]]:
    out = {}
    for path in sorted(MACROS.glob("*.cfg")):
        for block in re.split(r"(?m)^(?=\[)", path.read_text()):
            match = re.match(r"\[gcode_macro (\S+)\]", block)
            if match:
                out[match.group(1)] = set(re.findall(r"params\.([A-Z_]+)", block))
    return out


# --- the page as headings and tables -------------------------------------------

HEADING = re.compile(r"^(#{1,6}) (.*)$")


def section(text: str, title: re.Pattern) -> Optional[str]:
    """Text under the first heading matching `title`, up to the next heading of
    the same or a higher level."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        head = HEADING.match(line)
        if head and title.match(head.group(2)):
            level = len(head.group(1))
            body = []
            for later in lines[i + 1:]:
                h = HEADING.match(later)
                if h and len(h.group(1)) <= level:
                    break
                body.append(later)
            return "\n".join(body)
    return None


def subsection(text: Optional[str], title: str) -> str:
    if text is None:
        return ""
    return section(text, re.compile(re.escape(title) + "$")) or ""


def rows(text: str) -> List[List[str]]:
    """Body rows of the markdown tables in text, as cells."""
    out = []
    for line in text.splitlines():
        if not line.startswith("|") or re.match(r"^\|[\s|:-]+\|$", line):
            continue
        out.append([c.strip() for c in line.strip().strip("|").split("|")])
    return out


def first_cell_names(text: str) -> Dict[str, List[str]]:
    """`name` at the start of a row's first cell -> that row's cells."""
    out = {}
    for cells in rows(text):
        match = re.match(r"`([^`]+)`", cells[0])
        if match:
            out[match.group(1)] = cells
    return out


def slug(heading: str) -> str:
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(text: str) -> Set[str]:
    seen: Dict[str, int] = {}
    out = set()
    in_code = False
    for line in text.splitlines():
        if line.startswith("```"):
            in_code = not in_code
        head = None if in_code else HEADING.match(line)
        if head:
            base = slug(head.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


# --- the checks ---------------------------------------------------------------


# A section built on another's object ([flow_sensor_simulation NAME] is the
# flow sensor [flow_sensor NAME] on the twin): its own tables list what it
# adds; the options, commands and status it shares are the other's rows.
BUILT_ON = {"flow_sensor_simulation": "flow_sensor"}


def klippy_body(doc: str, module: str, prefix: bool) -> Optional[str]:
    name = f"[{module} NAME]" if prefix else f"[{module}]"
    return section(doc, re.compile(re.escape(f"`{name}` (klippy)") + "$"))


def klippy_problems(doc: str, sec: KlippySection) -> List[str]:
    name = f"[{sec.module} NAME]" if sec.prefix else f"[{sec.module}]"
    body = klippy_body(doc, sec.module, sec.prefix)
    if body is None:
        return [f"no heading '## `{name}` (klippy)'"]
    where = f"{name}:"
    problems = []
    documented = first_cell_names(subsection(body, "Options"))
    for option in sorted(sec.options - set(documented)):
        problems.append(f"{where} option `{option}` not in its Options table")
    for option in sorted(set(documented) - sec.options):
        problems.append(f"{where} Options table has `{option}`, the code reads no "
                        "such option")
    commands = first_cell_names(subsection(body, "G-code commands"))
    for command in sec.commands.values():
        cells = commands.get(command.name)
        if cells is None:
            problems.append(f"{where} command `{command.name}` not in its G-code table")
            continue
        row = " | ".join(cells)
        if command.help not in row:
            problems.append(f"{where} {command.name}: help text {command.help!r} "
                            "not in its row")
        for param in sorted(command.params):
            if not re.search(rf"\b{param}=", row):
                problems.append(f"{where} {command.name}: parameter {param}= not in "
                                "its row")
    for command in sorted(set(commands) - set(sec.commands)):
        problems.append(f"{where} G-code table has `{command}`, the code has no such "
                        "command")
    if sec.status is not None:
        status_body = body if sec.module not in BUILT_ON else klippy_body(
            doc, BUILT_ON[sec.module], sec.prefix)
        status = first_cell_names(subsection(status_body, "Status"))
        for field in sorted(sec.status - set(status)):
            problems.append(f"{where} status field `{field}` not in its Status table")
        for field in sorted(set(status) - sec.status):
            problems.append(f"{where} Status table has `{field}`, get_status has not")
    endpoints = first_cell_names(subsection(body, "API"))
    for endpoint in sorted(sec.endpoints - set(endpoints)):
        problems.append(f"{where} endpoint `{endpoint}` not in its API table")
    return problems


def moonraker_problems(doc: str, comp: Component) -> List[str]:
    body = section(doc, re.compile(r"Moonraker component `\[flowloop\]`"))
    if body is None:
        return ["no heading '## Moonraker component `[flowloop]` ...'"]
    problems = []
    options = first_cell_names(subsection(body, "Options"))
    for option in sorted(comp.options ^ set(options)):
        problems.append(f"moonraker: option `{option}` in the code or the Options "
                        "table but not both")
    table = {(cells[0], cells[1], cells[2])
             for cells in rows(subsection(body, "Endpoints"))
             if len(cells) > 2 and cells[1].startswith("`")}
    for method, path, rpc in sorted(comp.endpoints):
        if (method, f"`{path}`", f"`{rpc}`") not in table:
            problems.append(f"moonraker: no Endpoints row '{method} | `{path}` | "
                            f"`{rpc}`'")
    for method, path, rpc in sorted(table - {(m, f"`{p}`", f"`{r}`")
                                             for m, p, r in comp.endpoints}):
        problems.append(f"moonraker: Endpoints row {method} {path} {rpc} is not "
                        "registered")
    notified = set(first_cell_names(subsection(body, "Notifications")))
    for name in sorted(comp.notifications ^ notified):
        problems.append(f"moonraker: notification `{name}` in the code or the table "
                        "but not both")
    remote = set(first_cell_names(subsection(body, "Remote methods")))
    for name in sorted(comp.remote_methods ^ remote):
        problems.append(f"moonraker: remote method `{name}` in the code or the table "
                        "but not both")
    return problems


def cli_problems(doc: str, commands: Dict[str, Set[str]]) -> List[str]:
    body = section(doc, re.compile(r"Command line: `flowloop`$"))
    if body is None:
        return ["no heading '## Command line: `flowloop`'"]
    problems = []
    intro = body.split("\n### ", 1)[0]
    for option in sorted(commands[""]):
        if f"`{option}`" not in intro:
            problems.append(f"flowloop: top-level `{option}` not described")
    overview = {re.sub(r"[\[\]`]|\(.*", "", cells[0])
                for cells in rows(intro)}
    for path, options in commands.items():
        if not path:
            continue
        if " " not in path and path not in overview:
            problems.append(f"flowloop {path}: not in the command table")
        text = section(body, re.compile(re.escape(f"`flowloop {path}`") + "$"))
        if text is None:
            problems.append(f"flowloop {path}: no heading '### `flowloop {path}`'")
            continue
        if section(text, re.compile(r"`flowloop ")) is not None:
            text = text.split("\n#", 1)[0]   # a group: its own text only
        documented = {o for cells in rows(text)
                      for o in re.findall(r"`(--[a-z0-9-]+)", cells[0])}
        for option in sorted(options - documented):
            problems.append(f"flowloop {path}: option `{option}` not in its table")
        for option in sorted(documented - options):
            problems.append(f"flowloop {path}: table has `{option}`, the parser not")
    for line in body.splitlines():
        head = HEADING.match(line)
        match = head and re.match(r"`flowloop ([a-z -]+)`$", head.group(2))
        if match and match.group(1) not in commands:
            problems.append("heading for unknown subcommand "
                            f"'flowloop {match.group(1)}'")
    return problems


def macro_problems(doc: str, found: Dict[str, Set[str]]) -> List[str]:
    table = first_cell_names(subsection(doc, "Macros"))
    problems = []
    for name, params in sorted(found.items()):
        cells = table.get(name)
        if cells is None:
            problems.append(f"macro `{name}` not in the Macros table")
            continue
        row = " | ".join(cells)
        problems += [f"macro {name}: parameter {p}= not in its row"
                     for p in sorted(params) if not re.search(rf"\b{p}=", row)]
    return problems


def link_problems(doc: str) -> List[str]:
    problems = []
    headings: Dict[Path, Set[str]] = {}   # each page's anchors, read once
    for target in re.findall(r"\]\(([^)\s]+)\)", doc):
        if re.match(r"[a-z]+:", target):
            continue
        file, _, anchor = target.partition("#")
        path = (DOCS / file).resolve() if file else REFERENCE
        if not path.exists():
            problems.append(f"link to missing file {target}")
            continue
        if not anchor or path.suffix != ".md":
            continue
        if path not in headings:
            headings[path] = anchors(doc if path == REFERENCE else path.read_text())
        if anchor not in headings[path]:
            problems.append(f"link to missing heading {target}")
    return problems


@pytest.fixture(scope="module")
def facts():
    return klippy_sections(), moonraker_component(), cli_commands(), macros()


def problems(doc: str, facts) -> List[str]:
    sections, component, commands, found_macros = facts
    out = []
    for sec in sections:
        out += klippy_problems(doc, sec)
    out += moonraker_problems(doc, component)
    out += cli_problems(doc, commands)
    out += macro_problems(doc, found_macros)
    out += link_problems(doc)
    return out


# --- tests --------------------------------------------------------------------


def test_the_code_facts_are_found(facts):
    # Guards the parsers: if they found nothing, every check would pass.
    sections, component, commands, found_macros = facts
    by_module = {s.module: s for s in sections}
    sensor = by_module["flow_sensor"]
    assert sensor.prefix and not by_module["diff_ab_calibrate"].prefix
    simulation = by_module["flow_sensor_simulation"]
    assert "QUERY_FLOW_SENSOR" in sensor.commands and simulation.prefix
    assert set(simulation.commands) == {"SET_FLOW_SENSOR_SIMULATION"}
    assert {"SENSOR", "LENGTH", "SPEEDS", "MAX_SPREAD"} <= \
        sensor.commands["CALIBRATE_FLOW_SENSOR"].params
    assert {"cs_pin", "spi_speed", "sensor_type"} <= sensor.options
    assert "seed" in simulation.options and "seed" not in sensor.options
    assert "kinematics" not in by_module["diff_ab_calibrate"].options
    assert "FORCE" in by_module["diff_ab_calibrate"].commands[
        "DIFF_AB_CALIBRATE"].params
    assert sensor.endpoints == {"flow_sensor/dump_flow"}
    assert by_module["flowloop"].endpoints == {"flowloop/set_active_profile"}
    assert ("DELETE", "/server/flowloop/profile",
            "server.flowloop.delete_profile") in component.endpoints
    assert component.notifications == {"notify_flowloop_profile_changed",
                                       "notify_flowloop_nozzle_health"}
    assert "--wait-bed-equilibrium" in commands["ab-pylons"]
    assert "--output-dir" in commands["profile import"]
    assert "BED_TEMP" in found_macros["DIFF_AB_PRINT_PYLONS"]


def test_the_reference_names_everything_the_code_offers(facts):
    found = problems(REFERENCE.read_text(), facts)
    assert not found, "docs/reference.md is out of date:\n" + "\n".join(found)


def table_rows(doc: str, only_status: bool = False) -> List[int]:
    """Indexes of table body rows, except the contents table at the top; rows
    of the Status tables (checked against a running klippy in the klippy tier)
    only, or all others."""
    lines = doc.splitlines()
    first_section = next(i for i, line in enumerate(lines) if line.startswith("## "))
    out, heading = [], ""
    for i, line in enumerate(lines):
        head = HEADING.match(line)
        if head:
            heading = head.group(2).strip()
        if i > first_section and line.startswith("| ") \
                and not re.match(r"^\|[\s|:-]+\|$", line) \
                and not re.match(r"^\|[\s|:-]+\|$", lines[i + 1] if i + 1 < len(lines)
                                 else "") \
                and (heading == "Status") == only_status:
            out.append(i)
    return out


def test_deleting_any_row_of_the_reference_is_caught(facts):
    doc = REFERENCE.read_text()
    lines = doc.splitlines()
    uncaught = []
    for i in table_rows(doc):
        if not problems("\n".join(lines[:i] + lines[i + 1:]), facts):
            uncaught.append(lines[i])
    assert not uncaught, "rows whose loss the test misses:\n" + "\n".join(uncaught)


def test_a_link_to_a_missing_heading_is_caught(facts):
    doc = REFERENCE.read_text()
    assert problems(doc, facts) == []
    for link, broken in (("](#flowloop-info)", "](#flowloop-inf)"),
                         ("](install.md#firmware)", "](install.md#firmwar)")):
        assert link in doc
        found = problems(doc.replace(link, broken, 1), facts)
        assert found == [f"link to missing heading {broken[2:-1]}"]


def test_a_new_config_option_in_the_code_is_caught(facts):
    sections, component, commands, found_macros = facts
    grown = [dataclasses.replace(s, options=s.options | {"new_option"})
             if s.module == "diff_ab_calibrate" else s for s in sections]
    found = problems(REFERENCE.read_text(), (grown, component, commands,
                                             found_macros))
    assert found == ["[diff_ab_calibrate]: option `new_option` not in its Options "
                     "table"]


def test_a_changed_help_text_is_caught(facts):
    doc = REFERENCE.read_text()
    changed = doc.replace("Report grip, flows and errors of a flow sensor",
                          "Report grip")
    assert changed != doc
    assert problems(changed, facts) == [
        "[flow_sensor NAME]: QUERY_FLOW_SENSOR: help text 'Report grip, flows and "
        "errors of a flow sensor' not in its row"]


ADAPTER_WITH_HELPERS = """
class Source:
    def calibrate(self, gcmd, length):
        speeds = gcmd.get('SPEEDS', '1,2')
        return self._finish(gcmd)
    def _finish(self, gcmd):
        return gcmd.get_float('MAX_SPREAD', 2.)

def parse_wait(cmd):
    return cmd.get_int('IGNORED', 0)

class Sensor:
    def __init__(self, config):
        self.source = Source()
        gcode.register_mux_command('CALIBRATE_IT', 'SENSOR', 'x',
                                   self.cmd_CALIBRATE_IT,
                                   desc=self.cmd_CALIBRATE_IT_help)
    cmd_CALIBRATE_IT_help = "Calibrate it"
    def cmd_CALIBRATE_IT(self, gcmd):
        length = gcmd.get_float('LENGTH', 10.)
        self.source.calibrate(gcmd, length)
"""


def test_parameters_are_followed_into_the_helpers_a_command_hands_gcmd_to():
    tree = ast.parse(ADAPTER_WITH_HELPERS)
    commands = gcode_commands(PROJECT / "adapter.py", tree)
    assert commands["CALIBRATE_IT"].params == {"SENSOR", "LENGTH", "SPEEDS",
                                               "MAX_SPREAD"}
    assert commands["CALIBRATE_IT"].help == "Calibrate it"
