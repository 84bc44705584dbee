# flowloop component: uploaded G-code annotated for [autotemp].
#
# With `annotate_uploads: True` the annotator (`flowloop annotate`, the same
# core as the command line) is registered with the file manager's metadata
# processing, as Moonraker's own analysis component registers Klipper
# Estimator: it runs in Moonraker's metadata subprocess on upload and rescan,
# edits the file in place (a temporary file renamed over it), and
# annotate.MARKER_REGEX is its `ident`, so an annotated file is not processed
# again. A failure is logged by Moonraker and leaves the file as it was,
# printable. GET /server/flowloop/annotation tells whether a file is
# annotated and its peak flow (the annotator's summary line); POST
# /server/flowloop/annotation/check runs the registered command on a tiny file
# from this process, as the metadata script runs it (same environment and
# working directory), and says in one line why it fails (`flowloop doctor`).
# The command keeps the working directory off sys.path
# (flowloop.host.processor_check): Moonraker started from a home holding a
# flowloop/ clone would otherwise import that folder.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING, Any, Dict, List, Optional

from flowloop.gcode import annotate
from flowloop.host import processor_check

from ...common import RequestType, WebRequest
from . import args

if TYPE_CHECKING:
    from ...confighelper import ConfigHelper

PROCESSOR_NAME = "flowloop_autotemp"
DEFAULT_TIMEOUT_S = 600.0
TAIL_BYTES = 4096


def command(printer_cfg: Optional[str]) -> List[str]:
    """The processor's command line: this Python's flowloop, the file in place."""
    return processor_check.processor_command(sys.executable, printer_cfg)


class Processor:
    def __init__(self, config: ConfigHelper) -> None:
        self.server = config.get_server()
        self.enabled = config.getboolean("annotate_uploads", False)
        self.timeout_s = config.getfloat("annotate_timeout", DEFAULT_TIMEOUT_S,
                                         above=0.0)
        printer_cfg = config.get("annotate_printer_cfg", None)
        if printer_cfg is not None:
            printer_cfg = os.path.expanduser(printer_cfg)
        self.printer_cfg = printer_cfg
        self.file_manager = self.server.lookup_component("file_manager")
        self.config = {
            "name": PROCESSOR_NAME,
            "command": command(printer_cfg),
            "timeout": self.timeout_s,
            "version": f"v{annotate.FORMAT_VERSION}",
            "ident": {"regex": annotate.MARKER_REGEX, "location": "header"},
            "enabled": self.enabled,
        }
        self.registered_name: Optional[str] = None
        if self.enabled:
            self.file_manager.get_metadata_storage().register_gcode_processor(
                PROCESSOR_NAME, self.config)
            self.registered_name = PROCESSOR_NAME
        self.server.register_endpoint(
            "/server/flowloop/annotation", RequestType.GET,
            self._handle_annotation)
        self.server.register_endpoint(
            "/server/flowloop/annotation/check", RequestType.POST,
            self._handle_check)

    async def _handle_annotation(self, web_request: WebRequest) -> Dict[str, Any]:
        filename, path = args.gcode_file(web_request.get_args(),
                                         self.file_manager.get_directory("gcodes"))
        state = await self.server.get_event_loop().run_in_thread(
            _read_state, str(path))
        metadata = self.file_manager.get_metadata_storage().get(filename, {})
        processors = metadata.get("file_processors", [])
        return {"filename": filename, "annotate_uploads": self.enabled,
                "processed": PROCESSOR_NAME in processors, **state}


    async def _handle_check(self, web_request: WebRequest) -> Dict[str, Any]:
        """The registered command run on a tiny file, as Moonraker runs it."""
        problem = None
        if self.enabled:
            problem = await self.server.get_event_loop().run_in_thread(
                processor_check.check_processor, self.config["command"],
                min(self.timeout_s, processor_check.CHECK_TIMEOUT_S))
        return {"processor": PROCESSOR_NAME, "annotate_uploads": self.enabled,
                "ok": self.enabled and problem is None,
                "message": problem if self.enabled else
                "annotate_uploads is off: uploads are not annotated",
                "command": self.config["command"], "cwd": os.getcwd()}


def _read_state(path: str) -> Dict[str, Any]:
    with open(path, "rb") as f:
        head = f.read(annotate.HEADER_BYTES)
        f.seek(max(0, f.seek(0, os.SEEK_END) - TAIL_BYTES))
        summary = annotate.read_summary(f.read())
    return {"annotated": annotate.is_annotated(head),
            "peak_flow": None if summary is None else summary.peak_flow_mm3_s,
            "windows": None if summary is None else summary.windows,
            "print_time": None if summary is None else summary.print_time_s}
