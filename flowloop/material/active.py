"""Which profile is active on each extruder, and the rules that change it.

Moonraker stores one `ActiveProfile` per extruder (name and working point)
and klippy keeps an `Activation` (the profile itself and its working point).
Both are typed records; nothing reads them as loose dicts.

The Spoolman link's rules live here too: when the active spool changes
(`follow_spool`), the profile whose identity names that spool's Spoolman
filament becomes active on the spool's extruder (`spool_extruder`: the tool
that prints, or the one the link names), keeping that extruder's working point
(`keeping_working_point`); of several, the latest measured
(`profile_for_filament`, which the farm's path with `hotend:` uses too).
"""

from __future__ import annotations

import json
import math
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Tuple

import msgspec

from ..errors import FlowloopError
from .profile import (
    DEFAULT_WORKING_POINT,
    Profile,
    check_name,
    check_working_point,
    is_extruder_name,
)

WORKING_POINT_ACCEPTS = "a number from 0 (real print) to 1 (into air)"


class ActiveProfile(msgspec.Struct, frozen=True, kw_only=True,
                    forbid_unknown_fields=True):
    """What Moonraker stores for one extruder: which profile, at which WP."""

    name: str
    working_point: float = DEFAULT_WORKING_POINT

    def __post_init__(self) -> None:
        check_name(self.name)
        check_working_point(self.working_point)


class Activation(NamedTuple):
    """What klippy keeps for one extruder: the profile (capped to the heater),
    the working point, and the hotend's melt ratio against the profile that
    came with it (flowloop.control.nozzle_health.carried_ratio; None: none)."""

    profile: Profile
    working_point: float
    melt_ratio: Optional[float] = None


def active_from_stored(value: Any) -> Tuple[Dict[str, ActiveProfile], List[str]]:
    """The stored {extruder: {name, working_point}} record, validated entry by
    entry: (the valid entries, one line for each entry left out), so one
    damaged entry (say, written by an older flowloop) does not cost the rest."""
    if not isinstance(value, dict):
        raise FlowloopError(f"the active profiles record must be an object, got "
                            f"{type(value).__name__}")
    active: Dict[str, ActiveProfile] = {}
    skipped: List[str] = []
    for extruder, entry in value.items():
        if not is_extruder_name(extruder):
            skipped.append(f"{extruder!r} is not an extruder")
            continue
        try:
            active[extruder] = msgspec.convert(entry, ActiveProfile)
        except msgspec.ValidationError as e:
            skipped.append(f"{extruder}: {e}")
    return active, skipped


def active_to_stored(active: Mapping[str, ActiveProfile]) -> Dict[str, Any]:
    return {extruder: msgspec.to_builtins(entry)
            for extruder, entry in sorted(active.items())}


def number_arg(parameter: str, value: Any, accepts: str,
               lo: float = -math.inf, hi: float = math.inf) -> float:
    """A numeric request parameter (a JSON number or its text) within lo..hi.

    The refusal names the parameter, what it got and what it accepts, in one
    line: "working_point: got 'abc'; accepts a number from 0 ... to 1 ...".
    """
    number = value
    if isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            number = None
    if isinstance(number, bool) or not isinstance(number, (int, float)) \
            or not lo <= number <= hi:  # also refuses NaN
        prefix = f"{parameter}: " if parameter else ""  # argparse names it itself
        raise FlowloopError(f"{prefix}got {shown(value)}; accepts {accepts}")
    return float(number)


def shown(value: Any) -> str:
    """A request value as a refusal shows it: text as 'text', anything else as
    JSON (nan and inf as such), at most 40 characters."""
    got = repr(value) if isinstance(value, str) else _json_text(value)
    return got if len(got) <= 40 else got[:37] + "..."


def _json_text(value: Any) -> str:
    if isinstance(value, float):
        return repr(value)  # nan and inf too, which JSON would show as null
    try:
        return msgspec.json.encode(value).decode()
    except (TypeError, ValueError, OverflowError):
        return repr(value)


def working_point_arg(value: Any, parameter: str = "working_point") -> float:
    return number_arg(parameter, value, WORKING_POINT_ACCEPTS, 0.0, 1.0)


def extruder_arg(name: str) -> str:
    """An extruder name a request or a config option gives; refused in the
    one wording: "extruder9x" is not an extruder name (extruder, ...)."""
    if not is_extruder_name(name):
        raise FlowloopError(f"{json.dumps(name)} is not an extruder name "
                            f"(extruder, extruder1, ...)")
    return name


# spoolman_extruder's value that sends each spool to the tool that prints
ACTIVE_TOOL = "active"


def spool_extruder(linked: Optional[str], active: Optional[str]) -> str:
    """The extruder a newly active spool is for. Moonraker keeps one active
    spool per printer and Spoolman knows no tools, so on a toolchanger the
    spool is the printing tool's (the tool change macro sets it) unless the
    link names one extruder (`spoolman_extruder`); an active tool klippy did
    not say is `extruder`."""
    if linked is not None:
        return linked
    return active if is_extruder_name(active) else "extruder"


def spool_filament_id(spool: Any) -> Optional[int]:
    """The Spoolman filament id of a spool record (GET /v1/spool/<id>)."""
    filament = spool.get("filament") if isinstance(spool, dict) else None
    fid = filament.get("id") if isinstance(filament, dict) else None
    return fid if isinstance(fid, int) and not isinstance(fid, bool) else None


def profile_for_filament(profiles: Mapping[str, Profile],
                         filament_id: Optional[int]) -> Optional[Profile]:
    """The profile for a Spoolman filament, the one rule both paths of the
    link use (with or without `hotend:`): of the profiles naming it, the
    latest measured (`provenance.measured_at`); of equal times, the first
    by name, so the choice never depends on the order they were stored."""
    if filament_id is None:
        return None
    matches = [p for _, p in sorted(profiles.items())
               if p.identity.spoolman_filament_id == filament_id]
    # max keeps the first of equal keys: the first by name
    return max(matches, key=lambda p: p.provenance.measured_at, default=None)


def keeping_working_point(name: str, current: Optional[ActiveProfile],
                          default_wp: float = DEFAULT_WORKING_POINT
                          ) -> ActiveProfile:
    """`name` active on an extruder, at the working point that extruder
    already runs (one with nothing active yet: default_wp)."""
    wp = current.working_point if current is not None else default_wp
    return ActiveProfile(name=name, working_point=wp)


def follow_spool(spool: Any, profiles: Mapping[str, Profile],
                 current: Optional[ActiveProfile],
                 default_wp: float = DEFAULT_WORKING_POINT
                 ) -> Optional[ActiveProfile]:
    """What the linked extruder should run for a newly active spool, or None
    to leave it as it is (no profile names the spool's filament)."""
    profile = profile_for_filament(profiles, spool_filament_id(spool))
    if profile is None:
        return None
    return keeping_working_point(profile.name, current, default_wp)
