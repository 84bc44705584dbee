"""`flowloop doctor`: why flowloop does not work on a printer, one check a line.

The checks are pure functions over Facts, gathered by flowloop.cli.doctor from
Moonraker's API (and, on the printer itself, from the Klipper and Moonraker
trees through flowloop.host.install's planning: an empty install plan means
installed). A check that cannot be made from where the doctor runs says so
(status "skip") instead of guessing.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Dict, List, Optional, Tuple

from .. import __version__
from ..sensor import ems22
from . import firmware, install
from .info import PAGE_PATH, PANEL_URL, PANEL_WEBCAM
from .klipper_config import SIMULATION_SECTION

OK, FAIL, SKIP = "ok", "FAIL", "skip"

# Klipper's `git describe` of install.MIN_KLIPPER's commit (c89393cda is
# v0.13.0-568): judges a version string when the tree cannot be read.
MIN_KLIPPER_DESCRIBE = ((0, 13, 0), 568)

SENSOR_COMMAND = ems22.QUERY_CMD.split()[0]


def firmware_fix(host: str = "Klipper") -> str:
    return f"{firmware.firmware_hint(host)}; then FIRMWARE_RESTART"


INSTALL_FIX = ("run flowloop install from this checkout's virtualenv, then"
               " sudo systemctl restart klipper moonraker")
PROFILE_FIX = ("store a profile and activate it for the extruder: POST"
               " /server/flowloop/profile/activate {\"name\": ..., \"extruder\":"
               " ...} (docs/material_profiles.md)")


@dataclasses.dataclass(frozen=True)
class Check:
    name: str
    status: str          # OK, FAIL or SKIP
    detail: str
    fix: Optional[str] = None   # what to do, when it failed

    def line(self) -> str:
        text = f"{self.status:<4} {self.name}: {self.detail}"
        return text + (f"; fix: {self.fix}" if self.fix else "")


@dataclasses.dataclass(frozen=True)
class Facts:
    """What the doctor could find out; None where it could not look."""
    moonraker_url: str
    moonraker_error: Optional[str] = None    # Moonraker did not answer
    server_info: Optional[dict] = None       # GET /server/info
    endpoint_errors: Dict[str, Optional[str]] = dataclasses.field(
        default_factory=dict)                # flowloop endpoint -> error or None
    flowloop_info: Optional[dict] = None     # GET /server/flowloop/info
    printer_info: Optional[dict] = None      # GET /printer/info (klippy up)
    objects: Dict[str, dict] = dataclasses.field(default_factory=dict)
    # GET /machine/update/status's flowloop entry; None: no such entry
    update_status: Optional[dict] = None
    # On the printer only: the Klipper tree's problem (None: fine) and the
    # install plan left to do (empty: installed); None: not looked at.
    klipper_tree_problem: Optional[str] = None
    klipper_tree_checked: bool = False
    klipper_host: Optional[str] = None       # "Klipper" or "Kalico", from the tree
    install_pending: Optional[Tuple[str, ...]] = None
    install_error: Optional[str] = None
    moonraker_tree_checked: bool = True      # the plan covered Moonraker's link
    on_this_machine: bool = False            # Moonraker's URL is a loopback address
    # The Klipper checkout as Moonraker's update manager judges it (read here
    # with git, read-only): KlipperRepo; None: not a git checkout or not here.
    klipper_repo: Optional[KlipperRepo] = None
    # Moonraker's own entry for Klipper in /machine/update/status, if any.
    klipper_update_status: Optional[dict] = None
    # moonraker.conf's sections as Moonraker reports them (GET /server/config).
    moonraker_sections: Optional[Tuple[str, ...]] = None
    # klippy.log's last "Unable to open ... port" line since klippy started.
    mcu_port_error: Optional[str] = None
    # POST /server/flowloop/annotation/check: Moonraker ran its registered
    # annotator on a tiny file as it runs it on an upload; None: not asked
    # (no processor registered) or a component too old to answer.
    processor_run: Optional[dict] = None
    # GET /server/webcams/list's webcams; None: not asked or not answered.
    webcams: Optional[Tuple[dict, ...]] = None


# What Moonraker's update manager counts as source (git_deploy.py SRC_EXTS):
# such an untracked file makes the repo "not pristine".
MOONRAKER_SRC_EXTS = (".py", ".c", ".cpp", ".h", ".s", ".S", ".js", ".sh")


@dataclasses.dataclass(frozen=True)
class KlipperRepo:
    """A Klipper checkout as git_deploy.py reads it."""
    path: str
    version: str                        # git describe --always --tags --long
    modified: Tuple[str, ...] = ()      # `git status --porcelain` "M" lines
    untracked_source: Tuple[str, ...] = ()
    behind: Optional[int] = None        # commits on its upstream, as last fetched
    flowloop_edits: bool = False        # an older flowloop's blocks in src/

    @property
    def dirty(self) -> bool:
        return self.version.endswith("-dirty") or bool(self.modified)


def klipper_repo(path: str, describe: str, status: str, behind: Optional[str],
                 flowloop_edits: bool = False) -> KlipperRepo:
    """KlipperRepo from git's output, parsed as git_deploy.py parses it."""
    modified, untracked = [], []
    for line in status.splitlines():
        parts = line.strip().split(maxsplit=1)
        if len(parts) != 2:
            continue
        if parts[0] == "M":
            modified.append(parts[1])
        elif parts[0] == "??" and any(parts[1].endswith(ext)
                                      for ext in MOONRAKER_SRC_EXTS):
            untracked.append(parts[1])
    count = int(behind) if behind and behind.strip().isdigit() else None
    return KlipperRepo(path, describe.strip(), tuple(modified), tuple(untracked),
                       count, flowloop_edits)


# ---------------------------------------------------------------------------
# The checks, in the order a user fixes them


def check_klipper(facts: Facts) -> Check:
    info = facts.printer_info
    if facts.moonraker_error is not None:
        if not facts.klipper_tree_checked:
            return Check("klipper", SKIP, "not known: Moonraker did not answer")
        if facts.klipper_tree_problem is not None:
            return Check("klipper", FAIL, facts.klipper_tree_problem,
                         "update Klipper (cd ~/klipper; git pull), or pass"
                         " --klipper with the tree klippy runs from")
        repo = facts.klipper_repo
        where = f" {repo.version}" if repo else ""
        return Check("klipper", OK, f"{facts.klipper_host or 'Klipper'}{where}"
                     " here, supported (klippy not asked: Moonraker did not answer)")
    if info is None:
        return Check("klipper", FAIL, "klippy is not connected to Moonraker",
                     "sudo systemctl start klipper; read klippy.log if it stops")
    app = facts.klipper_host or info.get("app") or "Klipper"
    version = info.get("software_version") or "?"
    where = f"{app} {version} at {info.get('klipper_path')}"
    if facts.klipper_tree_checked:
        if facts.klipper_tree_problem is not None:
            return Check("klipper", FAIL, facts.klipper_tree_problem,
                         "update Klipper (cd ~/klipper; git pull; sudo systemctl"
                         " restart klipper), or pass --klipper with the tree"
                         " klippy runs from")
        return Check("klipper", OK, f"{where}, supported")
    supported = version_supported(version)
    if supported is None:
        return Check("klipper", SKIP, f"{where}: version not judged from here"
                     " (run flowloop doctor on the printer)")
    if not supported:
        return Check("klipper", FAIL, f"{where} is older than flowloop needs"
                     f" ({install.MIN_KLIPPER})",
                     "update Klipper: cd ~/klipper; git pull; sudo systemctl"
                     " restart klipper")
    return Check("klipper", OK, f"{where}, supported")


def version_supported(version: str) -> Optional[bool]:
    """A Klipper `git describe` version against MIN_KLIPPER_DESCRIBE; None
    when it is not one (a fork's scheme, or no git)."""
    m = re.match(r"v(\d+)\.(\d+)\.(\d+)(?:-(\d+))?", version)
    if m is None or m.group(1) != "0":  # Klipper's are v0.N.M; others not judged
        return None
    release = tuple(int(x) for x in m.group(1, 2, 3))
    ahead = int(m.group(4) or 0)
    return (release, ahead) >= MIN_KLIPPER_DESCRIBE


def check_links(facts: Facts) -> Check:
    if facts.install_error is not None:
        return Check("links", FAIL, facts.install_error, INSTALL_FIX)
    if facts.install_pending:
        shown = "; ".join(facts.install_pending[:3])
        more = len(facts.install_pending) - 3
        return Check("links", FAIL, "flowloop is not installed from this checkout:"
                     f" install would {shown}" + (f" (+{more} more)" if more > 0
                                                  else ""), INSTALL_FIX)
    running = _running_versions(facts)
    stale = {host: v for host, v in running.items() if v != __version__}
    if stale:
        return Check("links", FAIL, ", ".join(
            f"{host} runs flowloop {v or 'none'}" for host, v in stale.items())
            + f", this is {__version__}",
            "sudo systemctl restart klipper moonraker (or run the doctor of"
            " the flowloop they load)")
    if facts.install_pending is None:
        where = ("not checked: no Klipper tree found here (pass --klipper DIR)"
                 if facts.on_this_machine else "not checked from another machine"
                 " (run flowloop doctor on the printer)")
        return Check("links", SKIP, where + (
            f"; the hosts run flowloop {__version__}" if running else ""))
    unseen = ("" if facts.moonraker_tree_checked else "; Moonraker's link not"
              " checked: no ~/moonraker or ~/moonraker-env (pass --moonraker-dir)")
    return Check("links", OK, f"installed and pointing at flowloop {__version__}"
                 + unseen)


def _running_versions(facts: Facts) -> Dict[str, Optional[str]]:
    info = facts.flowloop_info
    if info is None:
        return {}
    running = {"moonraker": info.get("version")}
    if info.get("klippy_connected") and "flowloop" in facts.objects:
        running["klippy"] = info.get("klippy_version")
    return running


def check_firmware(facts: Facts) -> Check:
    info = facts.flowloop_info
    if info is None or not info.get("klippy_connected") or not info.get(
            "sensor_firmware"):
        return Check("firmware", SKIP, "not known: klippy's [flowloop] object"
                     " did not report its MCUs")
    firmware = info["sensor_firmware"]
    needed = ems22_mcus(facts) or sorted(firmware)
    lacking = [mcu for mcu in needed if not firmware.get(mcu)]
    if lacking:
        return Check("firmware", FAIL, f"{', '.join(repr(m) for m in lacking)}"
                     f" firmware lacks flowloop's {SENSOR_COMMAND} command",
                     firmware_fix(facts.klipper_host or "Klipper"))
    return Check("firmware", OK, f"{', '.join(repr(m) for m in needed)} firmware"
                 f" carries {SENSOR_COMMAND}")


def ems22_mcus(facts: Facts) -> List[str]:
    """The MCUs an EMS22 sensor is wired to (cs_pin "toolboard:PA4" ->
    "mcu toolboard"), from klippy's configfile settings."""
    mcus = set()
    for section, options in _settings(facts).items():
        if section.split()[0] != "flow_sensor" or options.get(
                "sensor_type") != "ems22":
            continue
        pin = str(options.get("cs_pin", ""))
        chip = pin.lstrip("^~!").partition(":")[0] if ":" in pin else "mcu"
        mcus.add("mcu" if chip == "mcu" else f"mcu {chip}")
    return sorted(mcus)


def check_moonraker(facts: Facts) -> Check:
    if facts.moonraker_error is not None:
        return Check("moonraker", FAIL, facts.moonraker_error,
                     "start Moonraker (sudo systemctl start moonraker) or pass"
                     " --moonraker URL (and --api-key)")
    server = facts.server_info or {}
    if "flowloop" in server.get("failed_components", []):
        return Check("moonraker", FAIL, "Moonraker failed to load the flowloop"
                     " component", "read moonraker.log for its error")
    if "flowloop" not in server.get("components", []):
        return Check("moonraker", FAIL, "Moonraker has no flowloop component",
                     "add a [flowloop] section to moonraker.conf, run flowloop"
                     " install, then sudo systemctl restart moonraker")
    failed = {path: err for path, err in facts.endpoint_errors.items() if err}
    if failed:
        return Check("moonraker", FAIL, "endpoints not answering: " + "; ".join(
            f"{path} {err}" for path, err in sorted(failed.items())),
            "read moonraker.log; sudo systemctl restart moonraker")
    return Check("moonraker", OK, f"component loaded, {len(facts.endpoint_errors)}"
                 " endpoints answering")


def check_sections(facts: Facts) -> Check:
    info = facts.printer_info
    if info is None:
        return Check("config", SKIP, "not known: klippy is not connected")
    state = info.get("state")
    unreachable = mcu_unreachable(facts)
    if unreachable is not None:
        return unreachable
    if state != "ready":
        # Klipper's own words name the section and option; its advice that
        # follows a blank line ("Once the underlying issue...") is dropped.
        message = str(info.get("state_message", "")).strip().split("\n\n")[0]
        return Check("config", FAIL, f"klippy stopped ({state}): "
                     + " ".join(message.split()),
                     "correct printer.cfg as the message says, then RESTART")
    sections = (facts.flowloop_info or {}).get("sections") or []
    return Check("config", OK, f"klippy ready; flowloop sections valid:"
                 f" {', '.join(sections) or 'none'}")


# klippy's own words when it cannot open an MCU's port (serialhdl.py)
_PORT_ERROR = re.compile(
    r"(mcu '[^']*': )?Unable to (open (serial |CAN )?port|connect)")
MCU_PORT_FIX = ("check the MCU's USB cable and power, and that [mcu] serial: in"
                " printer.cfg names a port ls /dev/serial/by-id/ lists; then"
                " FIRMWARE_RESTART")


def mcu_unreachable(facts: Facts) -> Optional[Check]:
    """klippy waiting for (startup) or given up on (error) an MCU whose port
    does not open: said in klippy's own words, which name the port."""
    info = facts.printer_info or {}
    state = info.get("state")
    message = str(info.get("state_message", ""))
    if state == "ready" or (facts.mcu_port_error is None
                            and not _PORT_ERROR.search(message)):
        return None
    said = facts.mcu_port_error or " ".join(message.split("\n\n")[0].split())
    ports = [f"[{name}] serial: {options['serial']}" for name, options
             in sorted(_settings(facts).items())
             if name.split()[0] == "mcu" and options.get("serial")]
    if ports and not any(o.split(": ", 1)[1] in said for o in ports):
        said += f" ({', '.join(ports)})"
    return Check("config", FAIL, f"klippy cannot reach its MCU ({state}): {said}",
                 MCU_PORT_FIX)


def check_sensors(facts: Facts) -> List[Check]:
    if (facts.printer_info or {}).get("state") not in (None, "ready"):
        return [Check(f"sensor {name.split()[-1]}", SKIP, "not known: klippy is"
                      " not ready") for name in sorted(facts.objects)
                if name.split()[0] == "flow_sensor"]
    checks = []
    for name, status in sorted(facts.objects.items()):
        if name.split()[0] != "flow_sensor":
            continue
        label = f"sensor {name.split()[-1]}"
        errors = status.get("errors") or {}
        counts = ", ".join(f"{k} {v}" for k, v in sorted(errors.items())) or "none"
        if status.get("fault"):
            checks.append(Check(label, FAIL, f"fault '{status['fault']}' (errors:"
                                f" {counts})", "check the sensor's wiring, cs_pin"
                                " and spi_mode (docs/flow_sensor.md); QUERY_FLOW_SENSOR"
                                " shows when it clears"))
        elif not status.get("samples") and (
                f"{SIMULATION_SECTION} {name.split()[-1]}" in _settings(facts)):
            checks.append(Check(label, SKIP, "simulated: it samples as klippy"
                                " generates extruder steps, none yet"))
        elif not status.get("samples"):
            checks.append(Check(label, FAIL, "no samples have arrived",
                                "check the wiring and cs_pin, and that the firmware"
                                " carries the sensor command; QUERY_FLOW_SENSOR"))
        else:
            checks.append(Check(label, OK, f"{status['samples']} samples,"
                                f" {status.get('sample_rate', 0):g}/s, no fault"
                                f" (errors: {counts})"))
    return checks


def check_profiles(facts: Facts) -> Check:
    if (facts.printer_info or {}).get("state") != "ready":
        return Check("profiles", SKIP, "not known: klippy is not ready")
    if "flowloop" not in facts.objects:
        return Check("profiles", SKIP, "not known: klippy's [flowloop] object is"
                     " not loaded")
    needing = extruders_needing_profile(facts)
    active = facts.objects["flowloop"].get("profiles") or {}
    missing = [e for e in needing if e not in active]
    if missing:
        return Check("profiles", FAIL, f"no active profile for {', '.join(missing)}"
                     " (it has a flow sensor or autotemp)", PROFILE_FIX)
    if not needing:
        return Check("profiles", OK, "no extruder has a flow sensor or autotemp")
    return Check("profiles", OK, ", ".join(
        f"{e} {active[e].get('name')!r}" for e in needing))


def extruders_needing_profile(facts: Facts) -> List[str]:
    extruders = set()
    for section, options in _settings(facts).items():
        if section.split()[0] in ("flow_sensor", SIMULATION_SECTION, "autotemp"):
            extruders.add(str(options.get("extruder", "extruder")))
    return sorted(extruders)


def check_gcode_processor(facts: Facts) -> Check:
    info = facts.flowloop_info
    if info is None:
        return Check("gcode processor", SKIP, "not known: no flowloop component")
    if "gcode_processor" not in info:
        return Check("gcode processor", SKIP, "not checked: this flowloop's"
                     " Moonraker component reports no G-code processor (run"
                     " flowloop annotate on a file before printing it)")
    if info["gcode_processor"]:
        run = facts.processor_run
        if run is not None and not run.get("ok"):
            return Check("gcode processor", FAIL, "registered"
                         f" ({info['gcode_processor']}) but it does not annotate"
                         f" a file as Moonraker runs it: {run.get('message')}",
                         "see docs/install.md; then sudo systemctl restart"
                         " moonraker and run flowloop doctor again")
        ran = ", and annotates a test file as Moonraker runs it" if run else ""
        return Check("gcode processor", OK,
                     f"registered ({info['gcode_processor']}){ran}")
    if not any(section.split()[0] == "autotemp" for section in _settings(facts)):
        return Check("gcode processor", SKIP, "off, and no [autotemp] needs it")
    return Check("gcode processor", FAIL, "[autotemp] is set up but uploads are"
                 " not annotated (moonraker.conf [flowloop] annotate_uploads is"
                 " off)", "set annotate_uploads: True in [flowloop] of"
                 " moonraker.conf and restart Moonraker, or run flowloop"
                 " annotate on each file")


def check_updates(facts: Facts) -> Check:
    """The checkout Moonraker's update manager pulls: a dirty or diverged one
    is refused by an update (and a diverged one reset if it diverged after
    Moonraker last looked), so it is named before the user clicks update."""
    if facts.moonraker_error is not None:
        return Check("updates", SKIP, "not known: Moonraker did not answer")
    server = facts.server_info or {}
    if "update_manager" in server.get("failed_components", []):
        return Check("updates", FAIL, "Moonraker failed to load its update"
                     " manager", "read moonraker.log for its error")
    if "update_manager" not in server.get("components", []):
        if "update_manager" in (facts.moonraker_sections or ()):
            return Check("updates", FAIL, "moonraker.conf has [update_manager]"
                         " but Moonraker has not loaded it", "read moonraker.log;"
                         " sudo systemctl restart moonraker")
        return Check("updates", SKIP, "Moonraker's update manager is not enabled"
                     " (no [update_manager] in moonraker.conf)")
    status = facts.update_status
    if status is None:
        return Check("updates", SKIP, "no [update_manager flowloop] in"
                     " moonraker.conf (flowloop install adds it to a git checkout's"
                     " install)")
    if status.get("is_dirty"):
        return Check("updates", FAIL, "the checkout has local changes: Moonraker"
                     " refuses to update it (" + "; ".join(status.get("warnings", []))
                     + ")", "in the flowloop checkout, keep them on a branch of your"
                     " own or drop them (git status), then refresh the updates in"
                     " Mainsail/Fluidd")
    diverged = [a for a in status.get("anomalies", []) if "diverged" in a]
    if diverged:
        return Check("updates", FAIL, "the checkout has commits origin has not:"
                     " Moonraker refuses to update it", "in the flowloop checkout,"
                     " move them to a branch of your own (git log"
                     " origin/main..HEAD), then git reset --hard origin/main")
    behind = status.get("commits_behind_count") or len(
        status.get("commits_behind", []))
    version = status.get("full_version_string") or status.get("version")
    if behind:
        return Check("updates", OK, f"{version}; {behind} commits to update"
                     " (Mainsail/Fluidd: update flowloop)")
    return Check("updates", OK, f"{version}, up to date with its origin")


def check_klipper_updates(facts: Facts) -> Check:
    """Klipper's checkout as Moonraker's update manager judges it: a modified
    tracked file makes it dirty, and Moonraker then refuses to update it (its
    Recover resets the file)."""
    repo = facts.klipper_repo
    if repo is None:
        status = facts.klipper_update_status
        if status is None:
            return Check("klipper updates", SKIP, "not known: no Klipper git"
                         " checkout here and no klipper entry in Moonraker's"
                         " update manager")
        repo = KlipperRepo(status.get("path", "klipper"), str(
            status.get("full_version_string") or status.get("version") or "?"),
            tuple(_modified_files(status.get("warnings", []))),
            behind=status.get("commits_behind_count"))
        if status.get("is_dirty") and not repo.modified:
            repo = dataclasses.replace(repo, version=repo.version + "-dirty")
    if repo.dirty:
        fix = ("flowloop install (it takes an older flowloop's edits of src/ out;"
               " firmware comes from flowloop firmware now)" if repo.flowloop_edits
               else f"in {repo.path}, keep your changes elsewhere and git checkout"
               " the files, then refresh the updates in Mainsail/Fluidd")
        return Check("klipper updates", FAIL, "dirty: Moonraker's update manager"
                     " refuses to update Klipper; modified: "
                     + (", ".join(repo.modified) or "(see git status)"), fix)
    note = (f"; untracked source files Moonraker lists as an anomaly: "
            f"{', '.join(repo.untracked_source)}" if repo.untracked_source else "")
    if repo.behind:
        return Check("klipper updates", OK, f"valid, {repo.version}, {repo.behind}"
                     " commits behind its upstream (as last fetched): update it in"
                     " Mainsail/Fluidd" + note)
    return Check("klipper updates", OK, f"valid, {repo.version}" + (
        ", up to date with its upstream as last fetched" if repo.behind == 0
        else "") + note)


PANEL_FIX = (f"flowloop install adds [webcam {PANEL_WEBCAM}] to moonraker.conf"
             f" (then restart Moonraker); or add a webcam of service iframe with"
             f" the URL {PANEL_URL} in Mainsail's or Fluidd's webcam settings")


def check_panel(facts: Facts) -> Check:
    """The live page as a panel of Mainsail's and Fluidd's dashboards: a
    webcam of service iframe at the page's path. An absolute URL works only
    where its host and port are the printer's as the browser reaches it."""
    if facts.webcams is None:
        return Check("dashboard panel", SKIP, "not known: Moonraker did not list"
                     " its webcams")
    pages = [w for w in facts.webcams
             if PAGE_PATH.rstrip("/") in str(w.get("stream_url", ""))]
    if not pages:
        return Check("dashboard panel", SKIP, "no webcam shows flowloop's live"
                     " page in the UI's dashboard", PANEL_FIX)
    cam = pages[0]
    name, url = cam.get("name", "?"), str(cam.get("stream_url", ""))
    if cam.get("service") != "iframe":
        return Check("dashboard panel", FAIL, f"webcam '{name}' shows the live"
                     f" page as service '{cam.get('service')}', which neither UI"
                     f" renders as a page", "set its service to iframe")
    if not cam.get("enabled", True):
        return Check("dashboard panel", FAIL, f"webcam '{name}' is disabled",
                     "enable it in the UI's webcam settings")
    where = ("relative to the UI's origin" if url.startswith("/")
             else "absolute: only a browser that reaches that host and port"
                  " shows it")
    return Check("dashboard panel", OK, f"webcam '{name}' (iframe) at {url},"
                 f" {where}")


def _modified_files(warnings: List[str]) -> List[str]:
    """The files Moonraker's "Repo is dirty" warning lists."""
    for warning in warnings:
        if "modified files:" in warning:
            listed = warning.split("modified files:", 1)[1]
            return re.findall(r"'([^']+)'", listed)
    return []


def _settings(facts: Facts) -> Dict[str, dict]:
    return (facts.objects.get("configfile") or {}).get("settings") or {}


def run_checks(facts: Facts) -> List[Check]:
    return ([check_klipper(facts), check_links(facts), check_moonraker(facts),
             check_sections(facts), check_firmware(facts)]
            + check_sensors(facts)
            + [check_profiles(facts), check_gcode_processor(facts),
               check_updates(facts), check_klipper_updates(facts),
               check_panel(facts)])


def exit_status(checks: List[Check]) -> int:
    return 1 if any(c.status == FAIL for c in checks) else 0
