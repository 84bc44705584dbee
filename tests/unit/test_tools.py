"""flowloop.control.tools: which tool's section acts on a toolchanger."""

from __future__ import annotations

import pytest

from flowloop.control.tools import PerTool, hand_back_target, m104_action, m104_extruder
from flowloop.errors import FlowloopError
from flowloop.host.klipper_config import section_extruder


def two_tools() -> PerTool[str]:
    table: PerTool[str] = PerTool("flowrate_limiter")
    table.add("flowrate_limiter", "extruder", "t0")
    table.add("flowrate_limiter extruder1", "extruder1", "t1")
    return table


def test_each_section_is_found_by_its_extruder():
    table = two_tools()
    assert table.get("extruder") == "t0" and table.get("extruder1") == "t1"
    assert table.get("extruder2") is None
    assert table.extruders == ["extruder", "extruder1"]
    assert table.members() == ["t0", "t1"]


def test_two_sections_for_one_extruder_are_the_second_ones_config_error():
    table = two_tools()
    with pytest.raises(FlowloopError) as e:
        table.add("flowrate_limiter", "extruder1", "again")
    assert str(e.value) == (
        "Section [flowrate_limiter], option extruder: extruder1 already has"
        " [flowrate_limiter extruder1] (one [flowrate_limiter] section per extruder)")


def test_a_command_goes_to_the_named_tool_else_the_printing_one():
    table = two_tools()
    assert table.pick("extruder1", "extruder") == "t1"
    assert table.pick(None, "extruder1") == "t1"
    assert table.pick(None, "extruder") == "t0"


def test_a_single_section_answers_whichever_tool_prints():
    table: PerTool[str] = PerTool("autotemp")
    table.add("autotemp", "extruder", "t0")
    assert table.pick(None, "extruder1") == "t0"


def test_a_tool_without_a_section_is_refused_naming_the_sections():
    table = two_tools()
    with pytest.raises(FlowloopError) as e:
        table.pick("extruder2", "extruder")
    assert str(e.value) == ("no [flowrate_limiter] acts on extruder2 (there is"
                            " [flowrate_limiter], [flowrate_limiter extruder1])")
    with pytest.raises(FlowloopError):
        table.pick(None, "extruder2")


def test_m104_names_its_tool_as_klippers_own_m104_does():
    assert m104_extruder(None, "extruder1") == "extruder1"
    assert m104_extruder(0, "extruder1") == "extruder"
    assert m104_extruder(1, "extruder") == "extruder1"
    assert m104_extruder(2, "extruder") == "extruder2"


@pytest.mark.parametrize("temp_c, printing, overrides, action", [
    (0.0, True, True, "stop"),       # heater off: always obeyed
    (0.0, False, False, "stop"),
    (175.0, True, True, "override"),  # the printing tool, planned
    (175.0, True, False, "pass"),     # not planning (yet): the user's
    (175.0, False, True, "pass"),     # an idle tool's standby is the user's
])
def test_m104_is_overridden_only_for_the_tool_that_prints_while_planned(
        temp_c, printing, overrides, action):
    assert m104_action(temp_c, printing, overrides) == action


def test_the_idle_tool_gets_the_users_target_back_never_a_higher_one():
    assert hand_back_target(175.0, 232.0) == 175.0   # the slicer's standby
    assert hand_back_target(240.0, 232.0) is None    # never raised
    assert hand_back_target(232.0, 232.0) is None    # nothing to change
    assert hand_back_target(None, 232.0) is None     # never asked: left alone


def test_a_per_tool_sections_name_says_its_extruder():
    assert section_extruder("flowrate_limiter extruder1") == "extruder1"
    assert section_extruder("autotemp") == "extruder"
    assert section_extruder("autotemp", "extruder2") == "extruder2"


def test_the_docs_example_is_the_config_the_klippy_tests_load():
    import re
    from pathlib import Path

    from flowloop.host.klipper_config import parse_config, read_config
    root = Path(__file__).resolve().parents[2]
    doc = (root / "docs" / "toolchangers.md").read_text()
    block = re.search(r"```ini\n(.*?)```", doc, re.S)[1]
    shown = parse_config(block)
    example = read_config(root / "config" / "toolchanger.cfg")
    assert shown.sections() and set(shown.sections()) <= set(example.sections())
    for section in shown.sections():
        assert shown.options(section) == example.options(section), section
    # the klippy tests load the example as it is
    assert "[include ../../config/toolchanger.cfg]" in (
        root / "tests" / "klippy" / "toolchanger.cfg").read_text()
