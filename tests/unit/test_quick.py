"""`make test-quick` picks the klippy tests of what changed (devtools/quick.py)."""

from __future__ import annotations

from devtools import quick


def chosen(*changed):
    return set(quick.klippy_tests(set(changed)))


def test_a_changed_klippy_module_selects_its_tests_and_no_others():
    tests = chosen("klippy_extras/autotemp.py")
    assert "tests/klippy/test_autotemp.py" in tests
    assert "tests/klippy/autotemp_macro.test" in tests
    assert all("/autotemp" in t or "/test_autotemp" in t for t in tests), tests


def test_a_changed_core_module_selects_the_modules_that_import_it():
    # the ems22 decoder is read by the flow sensor module, not by autotemp
    tests = chosen("flowloop/sensor/ems22.py")
    assert "tests/klippy/test_flow_sensor.py" in tests
    assert "tests/klippy/flow_sensor_linux.test" in tests
    assert not any("autotemp" in t or "endstop" in t for t in tests), tests


def test_an_import_through_another_core_module_counts():
    direct = quick._core_imports(quick.PROJECT / "klippy_extras/flowrate_limiter.py")
    reached = quick.reach("klippy_extras/flowrate_limiter.py", {})
    indirect = sorted(reached - direct - {"klippy_extras/flowrate_limiter.py"})
    assert indirect, "the limiter reaches core modules only through others"
    assert "tests/klippy/test_flowrate_limiter.py" in chosen(indirect[0])


def test_a_changed_test_config_selects_the_tests_of_its_module():
    tests = chosen("tests/klippy/flow_sensor_cal.cfg")
    assert "tests/klippy/flow_sensor_cal.test" in tests
    assert "tests/klippy/test_flow_sensor.py" in tests
    assert not any("flowrate" in t for t in tests)


def test_docs_alone_select_no_klippy_test():
    assert chosen("README.md", "docs/autotemp.md") == set()
