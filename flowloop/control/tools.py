"""Toolchangers and IDEX machines: which tool's section acts.

flowloop's per-tool sections follow Klipper's own pattern (`[extruder1]`,
`[tmc2209 extruder1]`): `[flowrate_limiter]` and `[autotemp]` act on
`extruder`, `[flowrate_limiter extruder1]` and `[autotemp extruder1]` on
`extruder1`. One object of each kind hands every move and command to the
section of the tool that prints; these are its rules, without Klipper.
"""

from __future__ import annotations

from typing import Dict, Generic, List, Optional, TypeVar

from ..errors import FlowloopError, option_message
from .heater_range import HeaterRange

Member = TypeVar("Member")


class PerTool(Generic[Member]):
    """The sections of one kind, one per extruder."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._by_extruder: Dict[str, Member] = {}
        self._sections: Dict[str, str] = {}   # extruder -> section

    def add(self, section: str, extruder: str, member: Member) -> None:
        """A section for an extruder; two sections for one extruder is the
        config error of the second (each would cap or heat the same tool)."""
        other = self._sections.get(extruder)
        if other is not None:
            raise FlowloopError(option_message(
                section, "extruder", f"{extruder} already has [{other}]"
                f" (one [{self.kind}] section per extruder)"))
        self._by_extruder[extruder] = member
        self._sections[extruder] = section

    def get(self, extruder: str) -> Optional[Member]:
        return self._by_extruder.get(extruder)

    @property
    def extruders(self) -> List[str]:
        return sorted(self._by_extruder)

    def members(self) -> List[Member]:
        return [self._by_extruder[name] for name in self.extruders]

    def pick(self, requested: Optional[str], active: str) -> Member:
        """The section a command means: EXTRUDER=name if given, else the
        active tool's, else the only one there is. Refused in one line that
        names the sections there are."""
        name = requested if requested is not None else active
        member = self._by_extruder.get(name)
        if member is None and requested is None and len(self._by_extruder) == 1:
            return next(iter(self._by_extruder.values()))
        if member is None:
            have = ", ".join(f"[{self._sections[e]}]" for e in self.extruders)
            raise FlowloopError(f"no [{self.kind}] acts on {name}"
                                f" (there is {have})")
        return member


def m104_extruder(tool: Optional[int], active: str) -> str:
    """The extruder an M104/M109 sets, as Klipper's own M104 decides it:
    T<n> names extruder (0) or extruder<n>; without T, the active one."""
    if tool is None:
        return active
    return "extruder" if tool == 0 else f"extruder{tool}"


def heater_off(temp_c: float) -> bool:
    """An M104/M109 that turns the heater off: always obeyed, and the
    tool's autotemp stands down."""
    return temp_c <= 0.0


def check_heater_target(temp_c: float, min_temp_c: float,
                        max_temp_c: float) -> float:
    """An M104/M109 S: 0 (off) or within the heater's min_temp..max_temp, as
    Klipper's heater checks it; checked before autotemp keeps it as the
    user's target or overrides it."""
    if not HeaterRange(min_temp_c, max_temp_c, "heater").accepts(temp_c):
        raise FlowloopError(f"S: must be 0 or from {min_temp_c:g} to"
                            f" {max_temp_c:g}, got {temp_c:g}")
    return temp_c


def m104_action(temp_c: float, printing: bool, overrides: bool) -> str:
    """What a tool's autotemp does with an M104 for its tool: 'stop' (a
    heater turned off is always obeyed, and autotemp stands down), 'override'
    (the tool prints and autotemp plans its heater: the value is kept as the
    user's, for when the tool goes idle), else 'pass' (Klipper's M104 sets
    it: an idle tool's standby is the user's)."""
    if heater_off(temp_c):
        return "stop"
    if printing and overrides:
        return "override"
    return "pass"


def hand_back_target(user_c: Optional[float], current_c: float) -> Optional[float]:
    """The target a tool's heater gets when its autotemp stands down at a
    tool change: the last one the user (or the slicer) asked for, never
    above the one it has (autotemp never raises an idle tool's heater);
    None: leave the heater as it is."""
    if user_c is None or user_c >= current_c:
        return None
    return user_c


def tool_objects(objects: List[str], settings: Dict[str, dict],
                 tool: str) -> Dict[str, Optional[str]]:
    """The klippy objects of one tool, from klippy's object list and its
    configfile settings (as Moonraker and the live page read them): the
    first `flow_sensor` on it, and its `flowrate_limiter` and `autotemp`
    (the per-tool section, else the plain one if it acts on this tool)."""
    def acts_on(section: str) -> bool:
        return (settings.get(section) or {}).get("extruder", "extruder") == tool

    def section(kind: str) -> Optional[str]:
        named = f"{kind} {tool}"
        if named in objects:
            return named
        return kind if kind in objects and acts_on(kind) else None
    sensors = [o for o in objects if o.startswith("flow_sensor ") and acts_on(o)]
    return {"sensor": sensors[0] if sensors else None,
            "limiter": section("flowrate_limiter"),
            "autotemp": section("autotemp")}
