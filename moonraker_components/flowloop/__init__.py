# flowloop: material profiles and flowloop status for Moonraker clients.
#
# Section [flowloop] in moonraker.conf. Installed by `flowloop install` as a
# link to this package in moonraker/components/ (Moonraker loads a component
# package like its own update_manager/). The thinking is in the flowloop
# package; the parts here each have one job:
#
#   store.py          one store per kind of record in Moonraker's database
#                     (profiles and active profiles, nozzle health), each
#                     with its lock, validation and schema version
#   profiles.py       store, delete, activate: write, tell klippy, notify
#   klippy_sync.py    klippy's copy of each extruder's active profile
#   spoolman_link.py  the active Spoolman spool chooses the active profile
#   info.py           what flowloop has loaded in Moonraker and klippy
#   api.py            the HTTP/JSON-RPC endpoints and klippy's remote method
#   processor.py      uploaded G-code annotated for [autotemp]
#   page.py           the live page (/server/flowloop/page/) and what it asks
#   reports.py        a flow report per job of Moonraker's history
#   nozzle_health.py  the hotend's melt capacity per job, a warning when it falls
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

from typing import TYPE_CHECKING

# isort: off
# first: the installed flowloop, not a folder of that name (importing.py)
from . import importing  # noqa: F401
# isort: on
from flowloop.errors import FlowloopError
from flowloop.material import profile as fl_profile
from flowloop.material import spoolman_field
from flowloop.material.active import ACTIVE_TOOL, extruder_arg

from .api import Api
from .info import Info
from .job_history import JobHistory
from .klippy_sync import KlippySync
from .nozzle_health import NozzleHealth
from .page import Page
from .processor import Processor
from .profiles import Profiles
from .reports import DEFAULT_REPORTS_TO_KEEP, Reports
from .spoolman_link import SpoolmanLink
from .store import NozzleHealthStore, ProfileStore, SchemaVersions

if TYPE_CHECKING:
    from ...confighelper import ConfigHelper


class Flowloop:
    def __init__(self, config: ConfigHelper) -> None:
        self.server = config.get_server()
        spoolman_link = config.getboolean("spoolman_link", False)
        # "active": each spool is the printing tool's (docs/toolchangers.md)
        spoolman_extruder = config.get("spoolman_extruder", ACTIVE_TOOL)
        try:
            spoolman_extruder = None if spoolman_extruder == ACTIVE_TOOL \
                else extruder_arg(spoolman_extruder)
        except FlowloopError as e:
            raise config.error(
                f"Section [flowloop], option spoolman_extruder: {e}") from None
        default_wp = config.getfloat(
            "working_point", fl_profile.DEFAULT_WORKING_POINT, minval=0.0, maxval=1.0)
        # what makes two printers the same for a profile kept in Spoolman
        hotend = config.get("hotend", None)
        if hotend is not None:
            try:
                spoolman_field.check_hotend(hotend)
            except FlowloopError as e:
                raise config.error(f"Section [flowloop], option hotend: {e}") from None
        database = self.server.lookup_component("database")
        versions = SchemaVersions(database)
        self.store = ProfileStore(database, versions)
        self.health_store = NozzleHealthStore(database, versions)
        self.klippy = KlippySync(self.server, self.store)
        self.profiles = Profiles(self.server, self.store, self.klippy)
        self.spoolman = None
        if spoolman_link:
            self.spoolman = SpoolmanLink(self.server, spoolman_extruder, default_wp,
                                         self.store, self.profiles, hotend)
        self.processor = Processor(config)
        self.info = Info(self.server, self.store, self.spoolman,
                         self.processor.registered_name)
        self.api = Api(self.server, self.store, self.profiles, self.info, default_wp)
        self.page = Page(self.server, self.store)
        self.job_history = JobHistory(config)
        self.reports = Reports(self.server, config.getint(
            "number_of_reports_to_keep", DEFAULT_REPORTS_TO_KEEP, minval=1),
            self.job_history)
        self.nozzle_health = NozzleHealth(self.server, self.store,
                                          self.health_store, hotend,
                                          self.job_history)
        # an activation starts the limiter's grip model from the hotend's
        # melt ratio for the profile from its last print
        self.klippy.melt_ratio_of = self.nozzle_health.carried_ratio

    async def component_init(self) -> None:
        # first: an older database's histories leave the profiles' namespace
        await self.health_store.load(self.store)
        await self.store.load()
        if self.spoolman is not None:
            self.spoolman.check_spoolman()

    async def close(self) -> None:
        if self.spoolman is not None:
            self.spoolman.close()


def load_component(config: ConfigHelper) -> Flowloop:
    return Flowloop(config)
