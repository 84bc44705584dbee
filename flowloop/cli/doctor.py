"""`flowloop doctor`: gather facts from Moonraker (and, on the printer, from the
Klipper and Moonraker trees), run flowloop.host.doctor's checks, print one
line each. Exit status 1 when a check fails."""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Dict, List, Optional, Tuple
from urllib.parse import quote, urlparse

from .. import __version__
from ..host import doctor, firmware, install, processor_check
from ..host.moonraker_api import DEFAULT_URL, MoonrakerApi
from .install import _default_moonraker as default_moonraker
from .install import default_klipper

# How long doctor waits for Moonraker to run the G-code processor on a tiny
# file: Moonraker's own check gives up first
PROCESSOR_CHECK_WAIT_S = processor_check.CHECK_TIMEOUT_S + 10.0
FLOWLOOP_ENDPOINTS = ("/server/flowloop/info", "/server/flowloop/profiles")
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "doctor", help="check that flowloop is installed and working, one line a check",
        description=f"flowloop {__version__}: check Klipper, the links, the MCU "
                    "firmware, Moonraker's component, the config, the sensors, the "
                    "active profiles and the G-code processor. Exit status 1 when "
                    "a check fails.")
    p.add_argument("--moonraker", default=DEFAULT_URL, metavar="URL",
                   help=f"Moonraker: a URL or HOST[:PORT] (default {DEFAULT_URL});"
                        f" from another machine the tree checks are skipped")
    p.add_argument("--api-key", default=os.environ.get("MOONRAKER_API_KEY"),
                   help="Moonraker API key (default: $MOONRAKER_API_KEY)")
    p.add_argument("--klipper", type=Path, default=None,
                   help="Klipper tree to check (default: the one klippy runs from, "
                        "when Moonraker is on this machine)")
    p.add_argument("--moonraker-dir", type=Path, default=None,
                   help="Moonraker checkout or virtualenv to check (default: "
                        "~/moonraker, else ~/moonraker-env, on this machine)")
    p.set_defaults(func=run)


class Client:
    """Moonraker as the doctor asks it: every answer (result, None) or (None,
    one-line reason), never raised (flowloop.host.moonraker_api)."""

    def __init__(self, url: str, api_key: Optional[str], timeout: float = 5.0):
        self.api = MoonrakerApi(url, api_key, timeout)
        self.url = self.api.url

    def get(self, path: str) -> Tuple[Optional[dict], Optional[str]]:
        return self.api.answer("GET", path)


def gather(client: Client, klipper: Optional[Path] = None,
           moonraker_dir: Optional[Path] = None) -> doctor.Facts:
    local = urlparse(client.url).hostname in LOOPBACK
    server_info, error = client.get("/server/info")
    if server_info is None:
        # Moonraker down on the printer: the trees are still here to check
        trees = _local_trees(klipper or default_klipper(), moonraker_dir) \
            if local else {}
        return doctor.Facts(client.url, moonraker_error=f"Moonraker at {client.url}:"
                            f" {error}", on_this_machine=local, **trees)
    endpoints: Dict[str, Optional[str]] = {}
    results: Dict[str, Optional[dict]] = {}
    for path in FLOWLOOP_ENDPOINTS:
        results[path], endpoints[path] = client.get(path)
    printer_info = objects = None
    if server_info.get("klippy_connected"):
        printer_info, _ = client.get("/printer/info")
        objects = _objects(client)
    update_status = klipper_status = None
    if "update_manager" in server_info.get("components", []):
        updates, _ = client.get("/machine/update/status")
        version_info = (updates or {}).get("version_info") or {}
        update_status = version_info.get("flowloop")
        klipper_status = version_info.get("klipper")
    webcams, _ = client.get("/server/webcams/list")
    config, _ = client.get("/server/config")
    sections = tuple((config or {}).get("config", {})) if config else None
    if klipper is None and local and printer_info:
        klipper = Path(printer_info["klipper_path"])
    port_error = None
    if local and printer_info and printer_info.get("state") != "ready":
        port_error = mcu_port_error(printer_info.get("log_file"))
    processor_run = None
    if (results["/server/flowloop/info"] or {}).get("gcode_processor"):
        # Moonraker runs its own processor command on a tiny file, in its
        # working directory and environment, as on an upload: a Python with
        # numpy starting on a small board takes seconds, so a longer wait
        slow = copy.copy(client.api)
        slow.timeout_s = PROCESSOR_CHECK_WAIT_S
        processor_run, error = slow.answer(
            "POST", "/server/flowloop/annotation/check")
        if error is not None and "HTTP 404" not in error:   # 404: older flowloop
            processor_run = {"ok": False, "message": error}
    return doctor.Facts(
        client.url, server_info=server_info, endpoint_errors=endpoints,
        flowloop_info=results["/server/flowloop/info"], printer_info=printer_info,
        objects=objects or {}, update_status=update_status,
        klipper_update_status=klipper_status, moonraker_sections=sections,
        mcu_port_error=port_error, processor_run=processor_run,
        webcams=None if webcams is None else tuple(webcams.get("webcams", [])),
        on_this_machine=local, **_local_trees(klipper, moonraker_dir, local))


def mcu_port_error(log_file: Optional[str]) -> Optional[str]:
    """klippy.log's last "Unable to open ... port" line since klippy last
    started (klippy's own words, naming the port), from the log's tail."""
    if not log_file:
        return None
    try:
        with open(log_file, "rb") as log:
            log.seek(0, os.SEEK_END)
            log.seek(max(0, log.tell() - 256 * 1024))
            tail = log.read().decode("utf-8", errors="replace")
    except OSError:
        return None
    tail = tail.rsplit("Starting Klippy...", 1)[-1]
    found = [line.strip() for line in tail.splitlines()
             if "Unable to open" in line and "port" in line]
    return found[-1] if found else None


def _local_trees(klipper: Optional[Path], moonraker_dir: Optional[Path],
                 local: bool = True) -> dict:
    """What the Klipper and Moonraker trees on this machine say, as Facts fields."""
    pending, install_error, moonraker_seen = _install_plan(klipper, moonraker_dir,
                                                           local)
    return dict(install_pending=pending, install_error=install_error,
                moonraker_tree_checked=moonraker_seen, **_klipper_tree(klipper))


def _objects(client: Client) -> Dict[str, dict]:
    listing, _ = client.get("/printer/objects/list")
    names = [n for n in (listing or {}).get("objects", [])
             if n.split()[0] in ("flowloop", "flow_sensor")]
    query = "&".join([quote(n) for n in names] + ["configfile=settings"])
    result, _ = client.get("/printer/objects/query?" + query)
    return (result or {}).get("status", {})


def _klipper_tree(klipper: Optional[Path]) -> dict:
    """What the Klipper (or Kalico) tree on this machine says, as Facts fields."""
    if klipper is None or not klipper.expanduser().exists():
        return {}
    klipper = klipper.expanduser()
    facts = {"klipper_tree_checked": True, "klipper_host": install.host_name(klipper),
             "klipper_repo": _klipper_repo(klipper)}
    try:
        install.check_klipper_tree(klipper)
        if not install.is_kalico(klipper):  # Kalico: its notes say what lacks
            install.check_klipper_version(klipper)
    except install.InstallError as e:
        facts["klipper_tree_problem"] = str(e)
    return facts


def _klipper_repo(klipper: Path) -> Optional[doctor.KlipperRepo]:
    """The checkout as Moonraker's update manager reads it (git_deploy.py's
    `git status --porcelain -b` and `git describe --dirty`)."""
    if not (klipper / ".git").exists():
        return None
    # not `describe --dirty` (Moonraker's): it rewrites the index whatever
    # --no-optional-locks says; status tells what makes it dirty instead
    describe = firmware.git(klipper, "describe", "--always", "--tags", "--long")
    status = firmware.git(klipper, "status", "--porcelain", "-b")
    if describe is None or status is None:
        return None
    behind = firmware.git(klipper, "rev-list", "--count", "HEAD..@{upstream}")
    kconfig = klipper / "src" / "Kconfig"
    edits = kconfig.is_file() and install.find_block(
        kconfig.read_text(errors="replace"), "sensor") is not None
    return doctor.klipper_repo(str(klipper), describe, status, behind, edits)


def _install_plan(klipper: Optional[Path], moonraker_dir: Optional[Path],
                  local: bool
                  ) -> Tuple[Optional[Tuple[str, ...]], Optional[str], bool]:
    """What flowloop install would still do (empty: installed), or its error,
    and whether Moonraker's tree was part of it; (None, None, False) when the
    trees are not on this machine."""
    if klipper is None or not klipper.expanduser().exists():
        return None, None, False
    if moonraker_dir is None and local:
        try:
            moonraker_dir = default_moonraker()
        except install.InstallError:
            moonraker_dir = None  # the links check says Moonraker's was not seen
    try:
        source = install.source_tree()
        changes: List[install.Change] = install.plan_klipper(klipper, source)
        if moonraker_dir is not None:
            changes += install.plan_moonraker(moonraker_dir, source)
    except install.InstallError as e:
        return None, str(e), False
    return tuple(change.what for change in changes), None, moonraker_dir is not None


def run(args) -> int:
    facts = gather(Client(args.moonraker, args.api_key), args.klipper,
                   args.moonraker_dir)
    checks = doctor.run_checks(facts)
    for check in checks:
        print(check.line())
    return doctor.exit_status(checks)
