"""flowloop doctor's checks over gathered facts (no printer needed)."""

from __future__ import annotations

import dataclasses

import pytest

from flowloop import __version__
from flowloop.cli import main
from flowloop.host import doctor, install
from flowloop.host.doctor import FAIL, OK, SKIP


def healthy(**changes) -> doctor.Facts:
    facts = doctor.Facts(
        "http://127.0.0.1:7125",
        server_info={"components": ["database", "flowloop"], "failed_components": [],
                     "klippy_connected": True},
        endpoint_errors={path: None for path in ("/server/flowloop/info",
                                                 "/server/flowloop/profiles")},
        flowloop_info={"version": __version__, "klippy_version": __version__,
                       "klippy_connected": True, "sections": ["flow_sensor sim"],
                       "sensor_firmware": {"mcu": True}},
        printer_info={"state": "ready", "state_message": "Printer is ready",
                      "software_version": "v0.13.0-730-g84104bbbd",
                      "klipper_path": "/opt/klipper"},
        objects={"flowloop": {"profiles": {"extruder": {"name": "PLA"}}},
                 "flow_sensor sim": {"samples": 1200, "sample_rate": 250.0,
                                     "fault": None, "errors": {}},
                 "configfile": {"settings": {
                     "flow_sensor_simulation sim": {"extruder": "extruder"}}}},
        klipper_tree_checked=True, install_pending=())
    return dataclasses.replace(facts, **changes)


def by_name(facts: doctor.Facts) -> dict:
    return {check.name: check for check in doctor.run_checks(facts)}


def failed(facts: doctor.Facts) -> dict:
    return {n: c for n, c in by_name(facts).items() if c.status == FAIL}


def test_a_healthy_printer_passes_every_check_but_the_missing_processor():
    checks = by_name(healthy())
    assert {n: c.status for n, c in checks.items()} == {
        "klipper": OK, "links": OK, "moonraker": OK, "config": OK,
        "firmware": OK, "sensor sim": OK, "profiles": OK,
        "gcode processor": SKIP, "updates": SKIP, "klipper updates": SKIP,
        "dashboard panel": SKIP}
    assert doctor.exit_status(list(checks.values())) == 0


PANEL = {"name": "flowloop", "service": "iframe", "enabled": True,
         "stream_url": "/server/flowloop/page/?panel=1", "source": "config"}


def test_the_dashboard_panel_install_adds_passes():
    check = by_name(healthy(webcams=(PANEL,)))["dashboard panel"]
    assert check.status == OK
    assert check.detail == ("webcam 'flowloop' (iframe) at /server/flowloop/page/"
                            "?panel=1, relative to the UI's origin")


def test_no_panel_says_what_is_missing_and_how_to_add_it():
    cam = {"name": "nozzle cam", "service": "mjpegstreamer",
           "stream_url": "/webcam/?action=stream"}
    check = by_name(healthy(webcams=(cam,)))["dashboard panel"]
    assert check.status == SKIP and "[webcam flowloop]" in check.fix
    assert "/server/flowloop/page/?panel=1" in check.fix


def test_a_panel_the_ui_cannot_render_fails():
    check = by_name(healthy(webcams=(dict(PANEL, service="mjpegstreamer"),)))[
        "dashboard panel"]
    assert check.status == FAIL and check.fix == "set its service to iframe"
    check = by_name(healthy(webcams=(dict(PANEL, enabled=False),)))[
        "dashboard panel"]
    assert check.status == FAIL
    absolute = dict(PANEL, stream_url="http://192.168.1.9:7125/server/flowloop/page/")
    check = by_name(healthy(webcams=(absolute,)))["dashboard panel"]
    assert check.status == OK and "absolute" in check.detail


def test_every_failure_names_its_fix_and_fails_the_exit_status():
    facts = healthy(install_pending=("link k/extras/flow_sensor.py -> x",))
    checks = doctor.run_checks(facts)
    assert doctor.exit_status(checks) == 1
    bad = [c for c in checks if c.status == FAIL]
    assert bad and all(c.fix and "; fix: " in c.line() for c in bad)
    assert all("fix" not in c.line() for c in checks if c.status == OK)


def test_a_missing_link_is_named_with_the_install_fix():
    bad = failed(healthy(install_pending=(
        "link /k/klippy/extras/flow_sensor.py -> /src/flow_sensor.py",)))
    assert list(bad) == ["links"]
    assert "flow_sensor.py" in bad["links"].detail
    assert "flowloop install" in bad["links"].fix


def test_hosts_running_another_flowloop_fail_the_link_check():
    info = dict(healthy().flowloop_info, klippy_version="0.0.1")
    bad = failed(healthy(flowloop_info=info))
    assert list(bad) == ["links"]
    assert "klippy runs flowloop 0.0.1" in bad["links"].detail
    assert "restart" in bad["links"].fix


def test_links_are_skipped_not_passed_from_another_machine():
    check = by_name(healthy(install_pending=None))["links"]
    assert check.status == SKIP and "another machine" in check.detail


def test_firmware_without_the_sensor_command_names_the_one_command_that_flashes_it():
    info = dict(healthy().flowloop_info, sensor_firmware={"mcu": False})
    bad = failed(healthy(flowloop_info=info))
    assert list(bad) == ["firmware"]
    assert "query_ems22" in bad["firmware"].detail
    fix = bad["firmware"].fix
    assert "flowloop firmware menuconfig" in fix and "CONFIG_WANT_SENSOR_EMS22" in fix
    assert "Support EMS22 filament flow sensor (flowloop)" in fix
    # Klipper's checkout has no EMS22 patch any more: its own make would not do
    assert "flowloop firmware flash FLASH_DEVICE=" in fix
    assert "cd ~/klipper" not in fix


def test_firmware_is_judged_on_the_mcu_an_ems22_sensor_is_wired_to():
    info = dict(healthy().flowloop_info,
                sensor_firmware={"mcu": False, "mcu toolboard": True})
    settings = {"flow_sensor a": {"sensor_type": "ems22", "cs_pin": "toolboard:PA4",
                                  "extruder": "extruder"}}
    objects = dict(healthy().objects, configfile={"settings": settings})
    assert by_name(healthy(flowloop_info=info, objects=objects))[
        "firmware"].status == OK
    settings["flow_sensor a"]["cs_pin"] = "PA4"
    assert by_name(healthy(flowloop_info=info, objects=objects))[
        "firmware"].status == FAIL


def test_an_invalid_section_quotes_klippys_message():
    message = ("Option 'sample_period' in section 'flow_sensor sim' must be"
               " below 0.05\n\nOnce the underlying issue is corrected, use the"
               " \"RESTART\" command to reload the config and restart the host"
               " software.\nPrinter is halted\n")
    bad = failed(healthy(printer_info=dict(healthy().printer_info, state="error",
                                           state_message=message)))
    assert "config" in bad
    assert "'sample_period' in section 'flow_sensor sim'" in bad["config"].detail
    assert "\n" not in bad["config"].line()
    assert "Once the underlying issue" not in bad["config"].line()
    assert by_name(healthy(printer_info=dict(healthy().printer_info, state="error",
                                             state_message=message)))[
        "profiles"].status == SKIP  # not judged on a klippy that stopped


def test_no_active_profile_for_an_extruder_with_a_sensor():
    objects = dict(healthy().objects, flowloop={"profiles": {}})
    bad = failed(healthy(objects=objects))
    assert list(bad) == ["profiles"]
    assert "extruder" in bad["profiles"].detail
    assert "/server/flowloop/profile/activate" in bad["profiles"].fix


def test_an_autotemp_extruder_needs_a_profile_too():
    settings = {"autotemp": {"extruder": "extruder1"}}
    objects = dict(healthy().objects, configfile={"settings": settings})
    bad = failed(healthy(objects=objects))
    assert "extruder1" in bad["profiles"].detail


def test_a_faulted_or_silent_sensor_fails():
    objects = dict(healthy().objects)
    objects["flow_sensor sim"] = {"samples": 50, "fault": "magnet_range",
                                  "errors": {"magnet_range": 12}}
    bad = failed(healthy(objects=objects))
    assert list(bad) == ["sensor sim"]
    assert "magnet_range 12" in bad["sensor sim"].detail
    objects["flow_sensor sim"] = {"samples": 0, "fault": None, "errors": {}}
    objects["configfile"] = {"settings": {"flow_sensor sim": {
        "sensor_type": "ems22", "cs_pin": "PA4"}}}
    assert "no samples" in failed(healthy(objects=objects))["sensor sim"].detail


def test_an_idle_simulated_sensor_without_samples_is_not_failed():
    objects = dict(healthy().objects)
    objects["flow_sensor sim"] = {"samples": 0, "fault": None, "errors": {}}
    check = by_name(healthy(objects=objects))["sensor sim"]
    assert check.status == SKIP and "simulated" in check.detail


def test_moonraker_without_the_component_or_unreachable():
    server = {"components": ["database"], "failed_components": []}
    assert "[flowloop]" in failed(healthy(server_info=server))["moonraker"].fix
    server = {"components": ["database"], "failed_components": ["flowloop"]}
    assert "moonraker.log" in failed(healthy(server_info=server))["moonraker"].fix
    errors = dict(healthy().endpoint_errors)
    errors["/server/flowloop/profiles"] = "HTTP 500 Internal Server Error"
    assert "/server/flowloop/profiles" in failed(healthy(
        endpoint_errors=errors))["moonraker"].detail
    down = doctor.Facts("http://printer:7125", moonraker_error="no answer")
    checks = by_name(down)
    assert checks["moonraker"].status == FAIL
    assert checks["klipper"].status == SKIP  # not blamed on klippy


@pytest.mark.parametrize("version, supported", [
    ("v0.13.0-568-gc89393cda", True), ("v0.13.0-730-g84104bbbd", True),
    ("v0.13.0-567-gabcdef", False), ("v0.13.0", False), ("v0.12.0-900-g1", False),
    ("v0.14.0", True), ("v0.14.0-2-gab", True), ("?", None), ("2025.1", None),
    ("v2025.03.01-5-gabc", None)])  # another scheme (a date): not judged
def test_a_version_string_is_judged_against_the_oldest_supported(version,
                                                                 supported):
    assert doctor.version_supported(version) is supported


def test_from_another_machine_an_old_klipper_is_refused_by_its_version():
    info = dict(healthy().printer_info, software_version="v0.13.0-12-g1234567")
    bad = failed(healthy(printer_info=info, klipper_tree_checked=False))
    assert "older than flowloop needs" in bad["klipper"].detail
    assert "git pull" in bad["klipper"].fix


def test_a_tree_problem_found_on_the_printer_wins_over_the_version_string():
    bad = failed(healthy(klipper_tree_problem="Klipper at /k is older than"
                                              " flowloop needs"))
    assert bad["klipper"].detail.startswith("Klipper at /k")


def with_autotemp(facts: doctor.Facts) -> doctor.Facts:
    objects = dict(facts.objects)
    settings = dict(objects["configfile"]["settings"],
                    autotemp={"extruder": "extruder"})
    objects["configfile"] = {"settings": settings}
    return dataclasses.replace(facts, objects=objects)


def test_the_processor_check_reads_the_components_report_when_there_is_one():
    info = dict(healthy().flowloop_info, gcode_processor=None)
    # off without [autotemp]: nothing needs it
    assert by_name(healthy(flowloop_info=info))["gcode processor"].status == SKIP
    # off with [autotemp]: uploads are not annotated, and the fix says how
    off = failed(with_autotemp(healthy(flowloop_info=info)))["gcode processor"]
    assert "annotate_uploads: True" in off.fix
    info["gcode_processor"] = "flowloop_autotemp"
    assert by_name(with_autotemp(healthy(flowloop_info=info)))[
        "gcode processor"].status == OK


def test_a_processor_that_fails_as_moonraker_runs_it_fails_the_check():
    """Issue 35.4: Moonraker started from a home holding the clone's flowloop/
    folder annotated nothing while doctor said the processor was registered."""
    info = dict(healthy().flowloop_info, gcode_processor="flowloop_autotemp")
    why = ("the G-code processor fails (exit 1) run from ~: ImportError:"
           " cannot import name '__version__'")
    check = by_name(healthy(flowloop_info=info, processor_run={
        "ok": False, "message": why}))["gcode processor"]
    assert check.status == FAIL and why in check.detail
    ran = by_name(healthy(flowloop_info=info, processor_run={"ok": True}))
    assert ran["gcode processor"].status == OK
    assert "annotates a test file" in ran["gcode processor"].detail


def test_the_command_exits_1_and_prints_one_line_a_check(capsys):
    code = main(["doctor", "--moonraker", "http://127.0.0.1:9"])
    lines = capsys.readouterr().out.splitlines()
    assert code == 1
    assert len(lines) == len(doctor.run_checks(doctor.Facts("x", "down")))
    assert any(line.startswith("FAIL moonraker: Moonraker at http://127.0.0.1:9")
               for line in lines)


def test_on_kalico_the_firmware_fix_names_its_firmware_extras_menu():
    info = dict(healthy().flowloop_info, sensor_firmware={"mcu": False})
    bad = failed(healthy(flowloop_info=info, klipper_host="Kalico"))
    assert "'Firmware Extras' -> 'Support EMS22" in bad["firmware"].fix
    assert "Optional features" not in bad["firmware"].fix
    assert "Optional features" in doctor.firmware_fix("Klipper")


def klipper_tree(root, kalico=False, new_enough=True):
    for rel in ("klippy/extras", "src"):
        (root / rel).mkdir(parents=True)
    for rel in ("klippy/klippy.py", "src/Makefile"):
        (root / rel).write_text("")
    (root / "src/Kconfig").write_text(f"{install.LIMITED_MENU}\nendmenu\n")
    (root / "klippy/mcu.py").write_text(
        "def register_serial_response(self):\n" if new_enough else "")
    if kalico:
        (root / "klippy/plugins").mkdir()
        (root / "klippy/plugins/__init__.py").write_text("")
        (root / "scripts").mkdir()
        (root / "scripts/find-firmware-extras.sh").write_text("")
    return root


def test_the_tree_on_the_printer_names_its_host_and_refuses_an_old_klipper(tmp_path):
    from flowloop.cli.doctor import _klipper_tree
    facts = _klipper_tree(klipper_tree(tmp_path / "k"))
    assert facts["klipper_host"] == "Klipper" and "klipper_tree_problem" not in facts
    old = _klipper_tree(klipper_tree(tmp_path / "old", new_enough=False))
    assert "older than flowloop needs" in old["klipper_tree_problem"]
    kal = klipper_tree(tmp_path / "kal", kalico=True, new_enough=False)
    kalico = _klipper_tree(kal)
    assert kalico["klipper_host"] == "Kalico"
    assert "klipper_tree_problem" not in kalico  # Kalico: not a refusal
    check = by_name(healthy(**kalico, printer_info=dict(
        healthy().printer_info, klipper_path=str(kal))))["klipper"]
    assert check.status == OK and check.detail.startswith("Kalico ")
    assert _klipper_tree(tmp_path / "nowhere") == {}


def with_updates(**entry) -> doctor.Facts:
    server = dict(healthy().server_info,
                  components=["database", "flowloop", "update_manager"])
    status = {"is_dirty": False, "anomalies": [], "warnings": [],
              "commits_behind": [], "full_version_string": "v0.1.0-3-gabcdef12"}
    return healthy(server_info=server, update_status=dict(status, **entry))


def test_updates_are_checked_only_where_moonraker_manages_them():
    assert by_name(healthy())["updates"].status == SKIP
    server = dict(healthy().server_info,
                  components=["flowloop", "update_manager"])
    check = by_name(healthy(server_info=server))["updates"]
    assert check.status == SKIP and "[update_manager flowloop]" in check.detail
    assert by_name(with_updates())["updates"].line() == (
        "ok   updates: v0.1.0-3-gabcdef12, up to date with its origin")
    assert "2 commits to update" in by_name(with_updates(
        commits_behind=[{"sha": "a"}, {"sha": "b"}]))["updates"].detail


def test_a_dirty_or_diverged_checkout_is_named_before_an_update():
    dirty = failed(with_updates(is_dirty=True, warnings=[
        "Repo is dirty.  Detected the following modified files: ['README.md']"]))
    assert list(dirty) == ["updates"]
    assert "README.md" in dirty["updates"].detail
    assert "branch of your own" in dirty["updates"].fix
    diverged = failed(with_updates(anomalies=["Repo has diverged from remote"]))
    assert "commits origin has not" in diverged["updates"].detail
    assert "git log origin/main..HEAD" in diverged["updates"].fix


def test_links_say_when_moonraker_s_tree_was_not_found():
    check = by_name(healthy(moonraker_tree_checked=False))["links"]
    assert check.status == OK and "pass --moonraker-dir" in check.detail
    assert "--moonraker-dir" not in by_name(healthy())["links"].detail


def test_on_the_printer_without_a_moonraker_tree_only_klipper_s_links_count(
        tmp_path, monkeypatch):
    from flowloop.cli import doctor as cli_doctor
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/moonraker, no ~/moonraker-env
    tree = klipper_tree(tmp_path / "k")
    pending, error, seen = cli_doctor._install_plan(tree, None, local=True)
    assert error is None and not seen
    assert pending and all("moonraker" not in what for what in pending)
    assert any("klippy/extras/flow_sensor " in what for what in pending)


def test_a_loopback_moonraker_that_does_not_answer_is_still_this_machine(
        tmp_path, capsys):
    # Moonraker down on the printer: the trees are here, so the links are checked.
    tree = klipper_tree(tmp_path / "k")
    components = tmp_path / "moonraker" / "moonraker" / "components"
    components.mkdir(parents=True)
    (components / "klippy_apis.py").write_text("")
    assert main(["doctor", "--moonraker", "http://127.0.0.1:9", "--klipper",
                 str(tree), "--moonraker-dir", str(tmp_path / "moonraker")]) == 1
    lines = {line.split(":")[0]: line for line in capsys.readouterr().out.splitlines()}
    assert "another machine" not in lines["FAIL links"]
    assert "install would link" in lines["FAIL links"]


def test_a_loopback_moonraker_without_a_tree_is_not_called_another_machine(
        tmp_path, capsys):
    assert main(["doctor", "--moonraker", "http://localhost:9", "--klipper",
                 str(tmp_path / "nowhere")]) == 1
    out = capsys.readouterr().out
    links = next(line for line in out.splitlines() if " links:" in line)
    assert "another machine" not in links and "--klipper" in links


# --- an MCU whose port is missing: klippy's words, naming the port -----------

PORT = "/dev/serial/by-id/usb-Klipper_stm32f446xx_1A0038-if00"
PORT_LINE = (f"mcu 'mcu': Unable to open serial port: [Errno 2] could not open port"
             f" {PORT}: [Errno 2] No such file or directory: '{PORT}'")


def without_mcu(state: str, message: str, **changes) -> doctor.Facts:
    info = dict(healthy().printer_info, state=state, state_message=message)
    objects = dict(healthy().objects)
    objects["flow_sensor sim"] = {"samples": 0, "fault": None, "errors": {}}
    objects["configfile"] = {"settings": dict(
        healthy().objects["configfile"]["settings"], mcu={"serial": PORT})}
    return healthy(printer_info=info, objects=objects, **changes)


def test_a_missing_mcu_port_is_said_in_klippys_words_naming_the_port():
    # klippy retries for 90 s ("startup"); its log names the port meanwhile
    checks = by_name(without_mcu("startup", "Printer is not ready\nThe klippy"
                                 " host software is attempting to connect.",
                                 mcu_port_error=PORT_LINE))
    assert checks["config"].status == FAIL
    assert PORT_LINE in checks["config"].detail
    assert "/dev/serial/by-id" in checks["config"].fix
    assert "correct printer.cfg" not in checks["config"].line()
    # the sensor is not blamed on its wiring while the MCU is away
    assert checks["sensor sim"].status == SKIP
    assert "cs_pin" not in "".join(c.line() for c in checks.values())


def test_after_klippy_gives_up_the_port_comes_from_printer_cfg():
    checks = by_name(without_mcu("error", "mcu 'mcu': Unable to connect\nOnce the"
                                 " underlying issue is corrected, use the"))
    line = checks["config"].line()
    assert "mcu 'mcu': Unable to connect" in line and f"serial: {PORT}" in line
    assert "cs_pin" not in "".join(c.line() for c in checks.values())


def test_the_port_line_is_read_from_klippy_log_since_the_last_start(tmp_path):
    from flowloop.cli.doctor import mcu_port_error
    log = tmp_path / "klippy.log"
    log.write_text(f"Starting Klippy...\n{PORT_LINE.replace(PORT, '/dev/old')}\n"
                   f"Starting Klippy...\nStarting serial connect\n{PORT_LINE}\n")
    assert mcu_port_error(str(log)) == PORT_LINE
    log.write_text("Starting Klippy...\nLoaded MCU 'mcu' 114 commands\n")
    assert mcu_port_error(str(log)) is None
    assert mcu_port_error(str(tmp_path / "none.log")) is None


# --- updates: Moonraker's update manager, and Klipper as it judges it --------

def test_updates_are_not_called_not_enabled_when_moonraker_did_not_answer():
    down = doctor.Facts("http://127.0.0.1:7125", moonraker_error="no answer")
    check = by_name(down)["updates"]
    assert check.status == SKIP and "not enabled" not in check.detail
    assert "Moonraker did not answer" in check.detail


def test_an_update_manager_in_moonraker_conf_that_is_not_loaded_fails():
    check = by_name(healthy(moonraker_sections=("server", "update_manager",
                                                "flowloop")))["updates"]
    assert check.status == FAIL and "moonraker.log" in check.fix
    server = dict(healthy().server_info, failed_components=["update_manager"])
    assert by_name(healthy(server_info=server))["updates"].status == FAIL


def test_a_local_klipper_checkout_is_recognised_when_moonraker_is_down(tmp_path,
                                                                        capsys):
    tree = klipper_tree(tmp_path / "k")
    main(["doctor", "--moonraker", "http://127.0.0.1:9", "--klipper", str(tree)])
    lines = capsys.readouterr().out.splitlines()
    klipper = next(line for line in lines if " klipper:" in line)
    assert klipper.startswith("ok   klipper: Klipper") and "not known" not in klipper


def repo(**changes) -> doctor.KlipperRepo:
    return dataclasses.replace(doctor.KlipperRepo(
        "~/klipper", "v0.13.0-730-g84104bbbd"), **changes)


def test_klipper_is_reported_as_moonrakers_update_manager_sees_it():
    ok = by_name(healthy(klipper_repo=repo(behind=0)))["klipper updates"]
    assert ok.status == OK and ok.detail.startswith("valid, v0.13.0-730")
    behind = by_name(healthy(klipper_repo=repo(behind=3)))["klipper updates"]
    assert behind.status == OK and "3 commits behind" in behind.detail
    dirty = by_name(healthy(klipper_repo=repo(
        version="v0.13.0-730-g84104bbbd-dirty",
        modified=("src/Kconfig", "src/Makefile"))))["klipper updates"]
    assert dirty.status == FAIL
    assert "dirty" in dirty.detail and "src/Kconfig, src/Makefile" in dirty.detail
    assert "git checkout" in dirty.fix
    old = by_name(healthy(klipper_repo=repo(modified=("src/Kconfig",),
                                            flowloop_edits=True)))
    assert "flowloop install" in old["klipper updates"].fix
    # from another machine: Moonraker's own entry for klipper
    remote = by_name(healthy(klipper_update_status={
        "is_dirty": True, "version": "v0.13.0-730", "warnings": [
            "Repo is dirty.  Detected the following modified files:"
            " ['src/Kconfig', 'src/Makefile']"]}))["klipper updates"]
    assert remote.status == FAIL and "src/Kconfig, src/Makefile" in remote.detail


def test_the_klipper_checkout_is_read_with_git_read_only(tmp_path):
    """git status refreshes the index unless told not to: the doctor must not
    write into ~/klipper/.git while Moonraker's git may run."""
    import subprocess

    from flowloop.cli.doctor import _klipper_repo
    tree = klipper_tree(tmp_path / "k")
    who = ["-c", "user.name=t", "-c", "user.email=t@t"]
    for args in (["init", "-q"], ["add", "."], [*who, "commit", "-qm", "k"]):
        subprocess.run(["git", "-C", str(tree), *args], check=True)
    (tree / "src" / "Kconfig").write_text("edited\n")
    (tree / "klippy" / "mine.py").write_text("")
    index = (tree / ".git" / "index").read_bytes()
    stat = (tree / ".git" / "index").stat().st_mtime_ns
    found = _klipper_repo(tree)
    assert found.modified == ("src/Kconfig",) and found.dirty
    assert found.untracked_source == ("klippy/mine.py",)
    assert (tree / ".git" / "index").read_bytes() == index
    assert (tree / ".git" / "index").stat().st_mtime_ns == stat
