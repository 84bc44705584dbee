"""A small client of a printer's Moonraker over plain HTTP: the flowloop
endpoints `flowloop profile store|activate|list|remove` use, and the
answers `flowloop doctor` gathers.

The address may be typed as Moonraker's URL (`http://printer.local:7125`) or
as a bare host with or without a port (`printer.local`, `192.168.1.20:7125`);
a refusal becomes one FlowloopError line with Moonraker's own message.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Dict, Optional, Tuple

from ..errors import FlowloopError

DEFAULT_URL = "http://127.0.0.1:7125"
DEFAULT_PORT = 7125
TIMEOUT_S = 10.0


def moonraker_url(address: str) -> str:
    """Moonraker's base URL from what a user types."""
    text = address.strip().rstrip("/")
    if not text:
        raise FlowloopError("--moonraker: empty address")
    if "://" not in text:
        text = "http://" + text
    parts = urllib.parse.urlsplit(text)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise FlowloopError(f"--moonraker: {address!r} is not an address of a "
                            f"Moonraker (http://HOST:PORT)")
    try:
        port = parts.port
    except ValueError:
        raise FlowloopError(f"--moonraker: {address!r} has a bad port") from None
    netloc = parts.netloc if port is not None or parts.scheme == "https" \
        else f"{parts.netloc}:{DEFAULT_PORT}"
    return urllib.parse.urlunsplit((parts.scheme, netloc, parts.path, "", ""))


class MoonrakerApi:
    def __init__(self, address: str = DEFAULT_URL, api_key: Optional[str] = None,
                 timeout_s: float = TIMEOUT_S) -> None:
        self.url = moonraker_url(address)
        self.headers = {"X-Api-Key": api_key} if api_key else {}
        self.timeout_s = timeout_s

    def request(self, method: str, path: str, query: Optional[Dict[str, str]] = None,
                body: Optional[Dict[str, Any]] = None) -> Any:
        """The `result` of one request; a refusal or no answer is one line."""
        result, error = self.answer(method, path, query, body)
        if error is not None:
            raise FlowloopError(f"{self.url}: {error}")
        return result

    def answer(self, method: str, path: str, query: Optional[Dict[str, str]] = None,
               body: Optional[Dict[str, Any]] = None) -> Tuple[Any, Optional[str]]:
        """(result, None), or (None, the one-line reason) when Moonraker
        refused or did not answer."""
        url = self.url + path
        if query:
            url += "?" + urllib.parse.urlencode(query)
        headers = dict(self.headers)
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        req = urllib.request.Request(url, data=data, headers=headers, method=method)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as resp:
                return json.loads(resp.read())["result"], None
        except urllib.error.HTTPError as e:
            return None, _refusal(e)
        except (urllib.error.URLError, OSError) as e:
            return None, f"no answer from Moonraker ({getattr(e, 'reason', e)})"
        except (ValueError, KeyError):
            return None, f"{path}: not a Moonraker answer"

    # --- the flowloop endpoints ------------------------------------------------
    def profiles(self) -> Dict[str, Any]:
        return self.request("GET", "/server/flowloop/profiles")

    def store(self, profile: Dict[str, Any]) -> Dict[str, Any]:
        return self.request("POST", "/server/flowloop/profile",
                            body={"profile": profile})

    def activate(self, name: str, extruder: str,
                 working_point: Optional[float]) -> Dict[str, Any]:
        body: Dict[str, Any] = {"name": name, "extruder": extruder}
        if working_point is not None:
            body["working_point"] = working_point
        return self.request("POST", "/server/flowloop/profile/activate", body=body)

    def remove(self, name: str) -> Dict[str, Any]:
        return self.request("DELETE", "/server/flowloop/profile", query={"name": name})


def _refusal(e: urllib.error.HTTPError) -> str:
    """Moonraker's message from the JSON body (the reason phrase may have
    been replaced), else the status line."""
    if e.code == 401:
        return "HTTP 401 unauthorized: is --api-key (or $MOONRAKER_API_KEY) right?"
    try:
        message = json.loads(e.read())["error"]["message"]
    except (ValueError, KeyError, TypeError, OSError):
        message = e.reason
    if e.code == 404 and str(message).strip().lower() in ("not found", ""):
        return ("HTTP 404: no such endpoint here; is [flowloop] in moonraker.conf"
                " (flowloop install)?")
    return f"HTTP {e.code} {message}"
