"""docs/reference.md against a running klippy: every flowloop section is loaded
from the configs the klippy tests use, and a macro reports what `get_status`
really returns and which options Klipper's configfile saw the section read.

This follows the code however it is split into helpers: the status is what a
client polling `printer[...]` gets, not what a parser finds in a dict literal.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Dict, Set

import pytest

from devtools.klippy_test import run_file, write_test
from tests.unit import test_reference_doc as ref

HERE = Path(__file__).resolve().parent

# One run per config; together they load every klippy_extras module, on both
# kinds of flow sensor source.
CONFIGS = ("flow_sensor_sim.cfg", "flow_sensor_both.cfg",
           "diff_ab_calibrate_corexy.cfg", "endstop_calibrate.cfg",
           "flowrate_limiter_loop.cfg", "measure_profile.cfg", "autotemp.cfg")

FACTS_MACRO = """
[gcode_macro FLOWLOOP_REFERENCE_FACTS]
gcode:
  {% set ns = namespace(out={}) %}
  {% set modules = params.MODULES.split(',') %}
  {% set settings = printer.configfile.settings %}
  {% for name in settings %}
    {% if name.split(' ')[0] in modules %}
      {% set status = printer[name].keys()|list if name in printer else [] %}
      {% set _ = ns.out.update({name: {'options': settings[name].keys()|list,
                                       'status': status}}) %}
    {% endif %}
  {% endfor %}
  {% for name in printer %}
    {% if name.split(' ')[0] in modules and name not in ns.out %}
      {% set _ = ns.out.update({name: {'options': [],
                                       'status': printer[name].keys()|list}}) %}
    {% endif %}
  {% endfor %}
  {action_respond_info("REFERENCE_FACTS " ~ (ns.out|tojson))}
"""

FACTS_LINE = re.compile(r"REFERENCE_FACTS (\{.*\})")


@pytest.fixture(scope="module")
def running(klipper_build, klippy_venv, tmp_path_factory):
    """module -> {'options': read in some run, 'status': its get_status fields
    (none for an object without get_status)}."""
    modules = sorted(ref.adapter_sources())
    found: Dict[str, Dict[str, Set[str]]] = {}
    for i, config in enumerate(CONFIGS):
        work = tmp_path_factory.mktemp("reference")  # klippy appends to its log
        _, test = write_test(
            work, f"facts{i}",
            f"FLOWLOOP_REFERENCE_FACTS MODULES={','.join(modules)}\n",
            cfg=f"[include {HERE / config}]\n{FACTS_MACRO}")
        log = run_file(test, klipper_build, klippy_venv, work)
        match = FACTS_LINE.search(log)
        assert match, f"{config}: no facts in the log\n{log[-3000:]}"
        for section, facts in json.loads(match.group(1)).items():
            module = section.split()[0]
            entry = found.setdefault(module, {"options": set(), "status": None})
            entry["options"] |= set(facts["options"])
            status = set(facts["status"])
            # One object, one set of fields, whatever its config or source.
            assert entry["status"] in (None, status), (
                f"[{section}] status fields differ between configs: "
                f"{sorted(entry['status'] ^ status)}")
            entry["status"] = status
    return found


@pytest.fixture(scope="module")
def facts(running):
    sections, component, commands, macros = (
        ref.klippy_sections(), ref.moonraker_component(), ref.cli_commands(),
        ref.macros())
    missing = sorted({s.module for s in sections} - set(running))
    assert not missing, (f"no config in CONFIGS loads {missing}: add one, so its "
                         "status is checked")
    for sec in sections:
        sec.status = running[sec.module]["status"]
    return sections, component, commands, macros


def test_every_status_field_is_in_the_reference(facts):
    found = ref.problems(ref.REFERENCE.read_text(), facts)
    assert not found, "docs/reference.md is out of date:\n" + "\n".join(found)


def test_klipper_saw_only_documented_options_read(running, facts):
    # The ast scan finds options by `config.get*('name')`; Klipper's own
    # access tracking is the ground truth for the configs above.
    sections = {s.module: s for s in facts[0]}
    base = {m: sections[b].options for m, b in ref.BUILT_ON.items()}
    unseen = {module: sorted(entry["options"] - sections[module].options
                             - base.get(module, set()))
              for module, entry in running.items()}
    assert not any(unseen.values()), f"options read but not found by ast: {unseen}"


def test_deleting_a_status_row_is_caught(facts):
    doc = ref.REFERENCE.read_text()
    lines = doc.splitlines()
    status_rows = ref.table_rows(doc, only_status=True)
    assert status_rows, "no Status rows found in docs/reference.md"
    uncaught = [lines[i] for i in status_rows
                if not ref.problems("\n".join(lines[:i] + lines[i + 1:]), facts)]
    assert not uncaught, "status rows whose loss the test misses:\n" + \
        "\n".join(uncaught)
