# flowloop component: the one reader of request arguments. Every endpoint
# (and klippy's remote method) reads its arguments here, so a missing or
# mistyped argument reads the same everywhere:
#
#   the file name is missing (argument 'filename')
#   the file name must be a string (argument 'filename': got 12)
#   working_point: got 'abc'; accepts a number from 0 (real print) to 1 (into air)
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict, Tuple

from flowloop.errors import FlowloopError
from flowloop.material import profile as fl_profile
from flowloop.material.active import extruder_arg, shown, working_point_arg

from ...common import ServerError, WebRequest
from .errors import one_line, quoted

DEFAULT_EXTRUDER = "extruder"


def refusal(msg: Any, code: int = 400) -> ServerError:
    return ServerError(one_line(msg), code)


def text(args: Dict[str, Any], key: str, what: str, default: Any = None) -> str:
    """A text argument; absent, null or empty is missing (then `default`, if
    one is given)."""
    value = args.get(key)
    if value is None or value == "":
        if default is not None:
            return default
        raise refusal(f"the {what} is missing (argument '{key}')")
    if not isinstance(value, str):
        raise refusal(f"the {what} must be a string (argument '{key}': got "
                      f"{shown(value)})")
    return value


def profile_name(web_request: WebRequest) -> str:
    name = text(web_request.get_args(), "name", "profile name")
    try:
        return fl_profile.check_name(name)
    except FlowloopError as e:
        raise refusal(e) from None


def extruder(args: Dict[str, Any], key: str = "extruder") -> str:
    """An extruder name (default `extruder`)."""
    try:
        return extruder_arg(text(args, key, "extruder name", DEFAULT_EXTRUDER))
    except FlowloopError as e:
        raise refusal(e) from None


def working_point(args: Dict[str, Any], default: float,
                  key: str = "working_point") -> float:
    """A working point; absent is `default`, null is refused like any other
    value that is not one."""
    try:
        return working_point_arg(args.get(key, default), key)
    except FlowloopError as e:
        raise refusal(e) from None


def gcode_file(args: Dict[str, Any], root: str) -> Tuple[str, Path]:
    """The `filename` argument and the file it names in the gcodes folder
    (root); 404 for none there."""
    filename = text(args, "filename", "file name")
    root = os.path.realpath(root)
    path = os.path.realpath(os.path.join(root, filename))
    if os.path.commonpath([path, root]) != root or not os.path.isfile(path):
        raise refusal(f"no G-code file named {quoted(filename)}", 404)
    return filename, Path(path)
