"""printer.cfg is read the way klippy reads it (includes, SAVE_CONFIG block)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.host import klipper_config
from flowloop.host.klipper_config import AUTOSAVE_HEADER, parse_config, read_config


def with_block(regular: str, *block_lines: str) -> str:
    return regular.rstrip("\n") + "\n" + AUTOSAVE_HEADER + "\n".join(
        ("#*# " + line).rstrip() for line in block_lines) + "\n"


def test_comments_and_repeated_sections_merge_like_klippy():
    cfg = parse_config(
        "[printer]\nkinematics: delta # trailing\nmax_velocity: 300 ; inline\n"
        "[stepper_a]\nposition_endstop: 300\n"
        "[printer]\nmax_velocity: 250\n#delta_radius: 99\n")
    assert cfg.get("printer", "kinematics") == "delta"
    assert cfg.getfloat("printer", "max_velocity") == 250.0
    assert not cfg.has_option("printer", "delta_radius")
    assert cfg.sections() == ["printer", "stepper_a"]


def test_save_config_block_values_are_in_force():
    # As SAVE_CONFIG writes it: the old value above is commented out.
    text = with_block("[stepper_a]\n#position_endstop: 300\narm_length: 250\n",
                      "[stepper_a]", "position_endstop = 301.25", "angle = 210.5", "",
                      "[delta_calibrate]", "height0 = 0.0")
    cfg = parse_config(text)
    assert cfg.getfloat("stepper_a", "position_endstop") == 301.25
    assert cfg.getfloat("stepper_a", "angle") == 210.5
    assert cfg.getfloat("stepper_a", "arm_length") == 250.0
    assert cfg.has_section("delta_calibrate")


def test_an_option_still_set_above_the_block_wins_as_in_klippy():
    text = with_block("[stepper_a]\nposition_endstop: 300\n",
                      "[stepper_a]", "position_endstop = 301.25", "angle = 211")
    cfg = parse_config(text)
    assert cfg.getfloat("stepper_a", "position_endstop") == 300.0
    assert cfg.getfloat("stepper_a", "angle") == 211.0


def test_a_hand_edited_block_is_ignored_as_in_klippy():
    text = with_block("[stepper_a]\nposition_endstop: 300\n",
                      "[stepper_a]", "angle = 211") + "[extra]\nkey: 1\n"
    cfg = parse_config(text)
    assert not cfg.has_option("stepper_a", "angle")
    assert cfg.has_section("extra")


def test_includes_resolve_relative_to_the_including_file_in_order(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "a.cfg").write_text("[stepper_a]\narm_length: 250\n")
    (tmp_path / "parts" / "b.cfg").write_text(
        "[stepper_a]\narm_length: 251\n[include ../more.cfg]\n")
    (tmp_path / "more.cfg").write_text("[stepper_b]\nangle: 331\n")
    main = tmp_path / "printer.cfg"
    main.write_text("[stepper_a]\narm_length: 249\nposition_endstop: 1\n"
                    "[include parts/*.cfg]\n[stepper_a]\nposition_endstop: 2\n")
    cfg = read_config(main)
    assert cfg.getfloat("stepper_a", "arm_length") == 251.0
    assert cfg.getfloat("stepper_a", "position_endstop") == 2.0
    assert cfg.getfloat("stepper_b", "angle") == 331.0
    assert [p.name for p in cfg.files] == ["printer.cfg", "a.cfg", "b.cfg", "more.cfg"]
    assert cfg.included_files_setting("stepper_a", "arm_length") == [
        (tmp_path / "parts" / name).resolve() for name in ("a.cfg", "b.cfg")]
    assert cfg.included_files_setting("stepper_a", "position_endstop") == []


def test_a_missing_include_or_an_include_loop_is_one_line(tmp_path):
    main = tmp_path / "printer.cfg"
    main.write_text("[include nothere.cfg]\n")
    with pytest.raises(FlowloopError, match="nothere.cfg does not exist"):
        read_config(main)
    main.write_text("[include maybe*.cfg]\n[printer]\n")  # an empty glob is fine
    assert read_config(main).has_section("printer")
    main.write_text("[include printer.cfg]\n")
    with pytest.raises(FlowloopError, match="recursive include"):
        read_config(main)


def test_unreadable_or_broken_files_are_one_line(tmp_path):
    with pytest.raises(FlowloopError, match="cannot read config file"):
        read_config(tmp_path / "absent.cfg")
    with pytest.raises(FlowloopError) as info:
        parse_config("position_endstop: 3\n")
    assert "\n" not in str(info.value)


def test_numbers_are_checked_naming_section_and_option():
    cfg = parse_config("[printer]\ndelta_radius: big\nmax_z: nan\n")
    with pytest.raises(FlowloopError, match="'delta_radius' in section 'printer'"):
        cfg.getfloat("printer", "delta_radius")
    with pytest.raises(FlowloopError, match="'max_z' in section 'printer'.*finite"):
        cfg.getfloat("printer", "max_z")
    with pytest.raises(FlowloopError, match="'absent' in section 'printer' must be"):
        cfg.getfloat("printer", "absent")
    assert cfg.getfloat("printer", "absent", 7.5) == 7.5


# --- the same answers as klippy's own reader, when a Klipper checkout exists ----


KLIPPY = Path.home() / "klipper" / "klippy"


def klippy_reader(text: str, tmp_path: Path):
    sys.path.insert(0, str(KLIPPY))
    try:
        import configfile  # klippy's module; stdlib only
    finally:
        sys.path.remove(str(KLIPPY))

    class Printer:
        def lookup_object(self, name):
            return type("Gcode", (), {"register_command": lambda *a, **k: None})()

        def get_start_args(self):
            return {"config_file": str(tmp_path / "printer.cfg")}

    (tmp_path / "printer.cfg").write_text(text)
    regular, _ = configfile.ConfigAutoSave(Printer()).load_main_config()
    return {s: dict(regular.items(s)) for s in regular.sections()}


options = st.sampled_from(["position_endstop", "angle", "arm_length"])
values = st.integers(0, 400).map(str)
entries = st.lists(st.tuples(st.sampled_from(["stepper_a", "stepper_b"]), options,
                             values, st.booleans()), max_size=6)


@pytest.mark.skipif(not (KLIPPY / "configfile.py").exists(), reason="no ~/klipper")
@given(regular=entries, block=entries)
def test_same_values_as_klippys_reader(tmp_path_factory, regular, block):
    lines = []
    for section, option, value, commented in regular:
        lines += [f"[{section}]", ("#" if commented else "") + f"{option}: {value}"]
    block_lines = []
    for section, option, value, _ in block:
        block_lines += [f"[{section}]", f"{option} = {value}"]
    text = with_block("\n".join(lines) + "\n", *block_lines) if block_lines else (
        "\n".join(lines) + "\n")
    ours = parse_config(text)
    theirs = klippy_reader(text, tmp_path_factory.mktemp("k"))
    assert {s: ours.options(s) for s in ours.sections()} == theirs


def test_save_plan_leaves_included_values_to_paste(tmp_path):
    (tmp_path / "steppers.cfg").write_text(
        "[stepper_a]\nposition_endstop: 300\n[stepper_b]\nstep_pin: PA1\n")
    main = tmp_path / "printer.cfg"
    main.write_text("[include steppers.cfg]\n[stepper_b]\nposition_endstop: 301\n")
    items = [("stepper_a", "position_endstop", "300.5"),
             ("stepper_b", "position_endstop", "300.7"),
             ("stepper_c", "position_endstop", "300.2")]
    staged, paste = klipper_config.save_plan(str(main), items)
    assert staged == items[1:]
    assert paste == [f"{(tmp_path / 'steppers.cfg').resolve()} sets these, which "
                     "SAVE_CONFIG cannot change; paste them there:",
                     "  [stepper_a]", "  position_endstop: 300.5"]


def test_the_save_report_lists_what_to_paste_then_what_save_config_stores():
    staged = [("stepper_b", "position_endstop", "298.8"),
              ("stepper_c", "position_endstop", "300.5")]
    paste = ["a.cfg sets these, which SAVE_CONFIG cannot change; paste them there:",
             "  [stepper_a]", "  position_endstop: 301.2"]
    assert klipper_config.save_report(staged, paste) == paste + [
        "Run SAVE_CONFIG to store [stepper_b] position_endstop,"
        " [stepper_c] position_endstop (Klipper restarts)."]
    assert klipper_config.save_report([], paste) == paste
    assert klipper_config.save_report([], []) == []


def test_an_included_file_with_indented_options_is_seen_setting_them(tmp_path):
    # klippy's reader (configparser) takes indented lines right after a header
    # as options, so SAVE_CONFIG would refuse to save them.
    (tmp_path / "steppers.cfg").write_text(
        "[stepper_a]\n  position_endstop: 300\n  arm_length: 250\n")
    main = tmp_path / "printer.cfg"
    main.write_text("[include steppers.cfg]\n")
    assert read_config(main).getfloat("stepper_a", "arm_length") == 250.0
    items = [("stepper_a", "position_endstop", "300.5")]
    staged, paste = klipper_config.save_plan(str(main), items)
    assert staged == [] and paste[-1] == "  position_endstop: 300.5"


def test_included_files_follow_includes_and_skip_the_save_config_block(tmp_path):
    (tmp_path / "hw").mkdir()
    (tmp_path / "hw" / "steppers.cfg").write_text(
        "[stepper_x]\nrotation_distance: 40 # belt\n[stepper_y]\nmicrosteps: 16\n")
    main = tmp_path / "printer.cfg"
    main.write_text(
        "[include hw/*.cfg]\n[printer]\nkinematics: corexy\n\n"
        "#*# <---------------------- SAVE_CONFIG ---------------------->\n"
        "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n"
        "#*#\n#*# [stepper_y]\n#*# rotation_distance = 40\n")
    config = read_config(main)
    assert config.included_files_setting("stepper_x", "rotation_distance") \
        == [(tmp_path / "hw" / "steppers.cfg").resolve()]
    assert config.included_files_setting("stepper_y", "rotation_distance") == []


def test_config_errors_name_section_and_option_in_one_format():
    assert klipper_config.option_message("endstop_calibrate", "radius", "too big") \
        == "Section [endstop_calibrate], option radius: too big"
    klipper_config.check_finite("x", {"a": 1.0, "b": None, "c": -0.0})
    for bad in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(FlowloopError) as e:
            klipper_config.check_finite("diff_ab_calibrate", {"d1": 10.0, "d2": bad})
        assert str(e.value) == ("Section [diff_ab_calibrate], option d2: must be a"
                                f" finite number, not {bad}")


class _ConfigError(Exception):
    pass


class _Section:
    """What finite_float uses of klippy's ConfigWrapper (its getfloat reads
    'nan' and 'inf' as Python does and lets them through its bounds)."""

    error = _ConfigError

    def __init__(self, options):
        self.options = options

    def get_name(self):
        return "diff_ab_calibrate"

    def getfloat(self, option, default=None, above=None, maxval=None):
        value = float(self.options.get(option, default))
        if above is not None and value <= above:
            raise _ConfigError(f"{option} must be above {above}")
        return value


@pytest.mark.parametrize("text", ["nan", "inf", "-inf"])
def test_a_float_option_refuses_nan_and_inf_as_a_config_error(text):
    with pytest.raises(_ConfigError) as e:
        klipper_config.finite_float(_Section({"d2": text}), "d2", 150.0)
    assert str(e.value) == ("Section [diff_ab_calibrate], option d2: must be a"
                            f" finite number, not {float(text)}")
    assert klipper_config.finite_float(_Section({}), "d2", 150.0, above=10.0) \
        == 150.0
    with pytest.raises(_ConfigError, match="above"):   # Klipper's own bounds
        klipper_config.finite_float(_Section({"d2": "5"}), "d2", above=10.0)


class _Printer:
    """What the lookup helpers use of klippy's Printer."""

    def __init__(self, objects):
        self.objects = objects

    def lookup_object(self, name, default=None):
        return self.objects.get(name, default)

    def lookup_objects(self, module=None):
        return [(name, obj) for name, obj in self.objects.items()
                if module is None or name == module
                or name.startswith(module + " ")]

    def config_error(self, message):
        return FlowloopError(message)


class _Extruder:
    def get_heater(self):
        return None


class _Sensor:
    def __init__(self, name, extruder_name):
        self.name, self.extruder_name = name, extruder_name


def test_one_extruder_lookup_for_the_sections():
    extruder = _Extruder()
    printer = _Printer({"extruder": extruder, "toolhead": object()})
    assert klipper_config.find_extruder(printer, "extruder") is extruder
    assert klipper_config.find_extruder(printer, "toolhead") is None
    assert klipper_config.find_extruder(printer, "extruder1") is None
    assert klipper_config.extruder_for(printer, "autotemp", "extruder") is extruder
    with pytest.raises(FlowloopError, match=r"^Section \[autotemp\], option "
                       r"extruder: 'toolhead' is not an extruder$"):
        klipper_config.extruder_for(printer, "autotemp", "toolhead")


def test_one_flow_sensor_lookup_by_name_else_by_extruder():
    a, b = _Sensor("a", "extruder1"), _Sensor("b", "extruder")
    printer = _Printer({"flow_sensor a": a, "flow_sensor b": b,
                        "flow_sensor": object()})  # no NAME: not one
    assert klipper_config.flow_sensors(printer) == [a, b]
    assert klipper_config.find_flow_sensor(printer, "extruder") is b
    assert klipper_config.find_flow_sensor(printer, "extruder", "a") is a
    assert klipper_config.find_flow_sensor(printer, "extruder", "c") is None
    assert klipper_config.find_flow_sensor(printer, "extruder2") is None


def test_the_host_facts_name_the_host_its_read_ahead_and_the_control():
    # read-ahead: each host's toolhead.py BUFFER_TIME_HIGH (the klippy tier
    # checks the table against the host's source)
    assert klipper_config.host_facts(False, "pid") == {
        "name": "Klipper", "buffer_time_s": 1.0, "heater_control": "pid"}
    assert klipper_config.host_facts(True, "mpc") == {
        "name": "Kalico", "buffer_time_s": 2.0, "heater_control": "mpc"}
