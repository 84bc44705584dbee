"""Material profiles kept on the filament in Spoolman, for a farm.

A profile is worth most where many printers use it: a farm measures a
filament once, and every printer with the same hotend uses that profile as
soon as a spool of it is loaded. flowloop keeps the profiles of a filament
in one extra field of Spoolman's filament entity (FIELD_KEY), keyed by a
hotend identity each printer declares (`hotend:` in moonraker.conf's
[flowloop], e.g. `revo_0.4`): two printers are "the same" for a profile
when their hotend, nozzle and heater melt alike, and their owner gives them
the same key.

The field's value, as Spoolman keeps extra fields, is JSON text: a JSON
string holding this module's document `{"flowloop": FIELD_VERSION,
"profiles": {hotend: profile}}` (each profile as flowloop stores it).

Two printers writing the same filament at once: each reads the field, puts
its profile in (merged), writes it and reads it back; a writer that finds
its entry missing or different merges again (up to WRITE_ATTEMPTS). For the
same hotend the later measurement wins (provenance.measured_at; equal: the
one written last), so both converge on the same field; the one whose
profile lost finds the other's in place and says so in its log.
"""

from __future__ import annotations

import json
import re
from typing import Any, Dict, Mapping, Optional

from ..errors import FlowloopError
from ..nesting import check_json_depth
from .profile import Profile, profile_from_dict, profile_to_dict

FIELD_KEY = "flowloop_profiles"
FIELD_NAME = "flowloop profiles"
FIELD_VERSION = 1
WRITE_ATTEMPTS = 3
HOTEND_KEY = re.compile(r"[a-z0-9][a-z0-9_.-]{0,63}")
# Spoolman's ids are SQL integers (PostgreSQL's and MySQL's 32-bit): a larger
# one is no filament it can hold (it answers 500, not 404, for it)
MAX_FILAMENT_ID = 2 ** 31 - 1
# Work Spoolman could not take (unreachable, too slow, a 5xx) is tried again
# after RETRY_FIRST_S, the wait doubling per failure up to RETRY_MAX_S, until
# it is done: a Spoolman that is slow but stays connected never makes
# Moonraker reconnect, which is the other moment it is tried.
RETRY_FIRST_S = 2.0
RETRY_MAX_S = 300.0


def check_hotend(key: Any) -> str:
    """A hotend identity: lower-case letters, digits, '_', '.', '-', up to 64."""
    if not isinstance(key, str) or not HOTEND_KEY.fullmatch(key):
        raise FlowloopError(
            f"hotend {key!r} is not a hotend key (lower-case letters, digits,"
            " '_', '.' and '-', e.g. revo_0.4)")
    return key


def check_filament_id(fid: int) -> int:
    """A filament id Spoolman can hold (1..MAX_FILAMENT_ID)."""
    if not 1 <= fid <= MAX_FILAMENT_ID:
        raise FlowloopError(f"Spoolman numbers filaments 1..{MAX_FILAMENT_ID}, "
                            f"not {fid}")
    return fid


def retry_delay_s(failures: int) -> float:
    """The wait before the next try after `failures` failed ones in a row."""
    return min(RETRY_MAX_S, RETRY_FIRST_S * 2.0 ** min(failures, 32))


def field_registration() -> Dict[str, Any]:
    """The body of Spoolman's POST /api/v1/field/filament/FIELD_KEY."""
    return {"name": FIELD_NAME, "field_type": "text", "order": 0}


def filament_label(filament: Mapping[str, Any]) -> str:
    return f"Spoolman filament {filament.get('id')} ({filament.get('name')!r})"


def read_field(filament: Mapping[str, Any]) -> Dict[str, Profile]:
    """{hotend: profile} from a Spoolman filament (as its API returns it);
    {} when it has no flowloop field. Bad data (hand-edited, another
    version's document, a profile that fails validation) raises one line
    that names the filament."""
    extra = filament.get("extra") or {}
    raw = extra.get(FIELD_KEY) if isinstance(extra, Mapping) else None
    if raw in (None, "", '""'):
        return {}
    where = f"{filament_label(filament)}: its {FIELD_KEY} field"
    if not isinstance(raw, str):
        raise FlowloopError(f"{where} is not JSON text")
    try:
        # nested too deep for json (RecursionError): refused before decoding
        check_json_depth(raw, where)
        text = json.loads(raw)
        if isinstance(text, str):
            check_json_depth(text, where)
        document = json.loads(text) if isinstance(text, str) else text
    except (TypeError, ValueError) as e:
        raise FlowloopError(f"{where} is not JSON ({e})") from None
    if not isinstance(document, dict) or document.get("flowloop") != FIELD_VERSION:
        raise FlowloopError(f"{where} is not a flowloop document of version"
                            f" {FIELD_VERSION}")
    profiles = document.get("profiles")
    if not isinstance(profiles, dict):
        raise FlowloopError(f"{where} has no profiles object")
    out = {}
    for hotend, data in profiles.items():
        try:
            check_hotend(hotend)
            out[hotend] = profile_from_dict(data)
        except FlowloopError as e:
            raise FlowloopError(f"{where}, hotend {hotend!r}: {e}") from None
    return out


def field_value(profiles: Mapping[str, Profile]) -> str:
    """The extra field's value for Spoolman (JSON text of a JSON string)."""
    document = {"flowloop": FIELD_VERSION,
                "profiles": {hotend: profile_to_dict(p)
                             for hotend, p in sorted(profiles.items())}}
    return json.dumps(json.dumps(document, sort_keys=True))


def newer(candidate: Profile, current: Optional[Profile]) -> bool:
    """Whether candidate replaces current for a hotend: a later measurement,
    or the same time (the writer's own is the one written last)."""
    if current is None:
        return True
    return candidate.provenance.measured_at >= current.provenance.measured_at


def merged(current: Mapping[str, Profile], hotend: str,
           profile: Profile) -> Dict[str, Profile]:
    """The field with `profile` for `hotend`, unless it holds a later one."""
    out = dict(current)
    if newer(profile, out.get(hotend)):
        out[hotend] = profile
    return out


def filament_id_of(profile: Profile) -> Optional[int]:
    """The Spoolman filament a profile is for, if it names one."""
    return profile.identity.spoolman_filament_id
