"""`flowloop info`: ask a running Moonraker what flowloop has loaded."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

from ..errors import FlowloopError


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


def describe(info: dict) -> str:
    lines = [f"flowloop {info['version']} in Moonraker"]
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
