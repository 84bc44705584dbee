"""`flowloop info` (and `make demo`) in words: what Moonraker answered."""

from __future__ import annotations

from flowloop.host.info import describe

INFO = {"version": "0.1.0", "klippy_connected": True, "klippy_version": "0.1.0",
        "sections": ["flow_sensor filament", "flowrate_limiter"],
        "sensor_firmware": {"mcu": True, "toolboard": False}, "profiles": 3,
        "active_profiles": {"extruder1": {"name": "petg", "working_point": 0.25},
                            "extruder": {"name": 'pla "red"', "working_point": 0.5}},
        "spoolman_link": True}


def test_info_names_the_active_profiles_and_the_spoolman_link():
    text = describe(INFO)
    assert ('profiles: 3 stored; active: extruder "pla \\"red\\"" at working point '
            '0.5, extruder1 "petg" at working point 0.25; follows the Spoolman spool'
            ) in text.splitlines()


def test_info_says_what_each_mcu_lacks():
    text = describe(INFO)
    assert "toolboard: EMS22 sensor command missing (rebuild the firmware)" in text
    assert "mcu: EMS22 sensor command present" in text
    assert "sections: flow_sensor filament, flowrate_limiter" in text


def test_info_without_klippy_or_profiles():
    text = describe({"version": "0.1.0", "klippy_connected": False, "profiles": 0,
                     "active_profiles": {}, "spoolman_link": False})
    assert text.splitlines() == ["flowloop 0.1.0 in Moonraker",
                                 "profiles: 0 stored; active: none",
                                 "klippy: not connected"]


def test_info_given_the_moonraker_url_names_the_live_page():
    text = describe(INFO, "http://printer.local:7125/")
    assert text.splitlines()[1] == \
        "live page: http://printer.local:7125/server/flowloop/page/"
    assert "live page" not in describe(INFO)
