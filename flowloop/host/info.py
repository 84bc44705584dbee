"""`flowloop info`: ask a running Moonraker what flowloop has loaded."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from typing import Optional

from ..errors import FlowloopError

# Where the component serves the live page (flowloop.host.live_page).
PAGE_PATH = "/server/flowloop/page/"
# The live page laid out for a dashboard panel (Mainsail's and Fluidd's
# webcam of service iframe). Relative: both UIs resolve it against the origin
# they are served from, which behind the usual nginx passes /server/ to
# Moonraker (docs/ui.md).
PANEL_URL = PAGE_PATH + "?panel=1"
PANEL_WEBCAM = "flowloop"


def page_url(moonraker_url: str) -> str:
    """Where a browser opens the live page of the Moonraker at moonraker_url."""
    return moonraker_url.rstrip("/") + PAGE_PATH


def fetch_info(url: str, timeout: float = 5.0) -> dict:
    try:
        with urllib.request.urlopen(url.rstrip("/") + "/server/flowloop/info",
                                    timeout=timeout) as resp:
            return json.loads(resp.read())["result"]
    except urllib.error.HTTPError as e:
        if e.code == 404:
            raise FlowloopError(f"{url}: Moonraker has no flowloop component; run "
                                f"'flowloop install' and add [flowloop] to "
                                f"moonraker.conf") from None
        raise FlowloopError(f"{url}: HTTP {e.code} {e.reason}") from None
    except (urllib.error.URLError, OSError) as e:
        raise FlowloopError(f"{url}: cannot reach Moonraker ({e})") from None


def describe(info: dict, moonraker_url: Optional[str] = None) -> str:
    """What Moonraker answered, in words; with its URL, where the live page is."""
    lines = [f"flowloop {info['version']} in Moonraker"]
    if moonraker_url is not None:
        lines.append(f"live page: {page_url(moonraker_url)}")
    active = info.get("active_profiles") or {}
    lines.append(f"profiles: {info.get('profiles', 0)} stored; active: " + (", ".join(
        f"{ext} {json.dumps(entry['name'])} at working point {entry['working_point']:g}"
        for ext, entry in sorted(active.items())) or "none")
        + ("; follows the Spoolman spool" if info.get("spoolman_link") else ""))
    if not info["klippy_connected"]:
        lines.append("klippy: not connected")
        return "\n".join(lines)
    sections = ", ".join(info["sections"]) or "none"
    lines.append(f"klippy: flowloop {info.get('klippy_version') or 'not loaded'}; "
                 f"sections: {sections}")
    for mcu, has in sorted(info["sensor_firmware"].items()):
        lines.append(f"{mcu}: EMS22 sensor command "
                     f"{'present' if has else 'missing (rebuild the firmware)'}")
    return "\n".join(lines)
