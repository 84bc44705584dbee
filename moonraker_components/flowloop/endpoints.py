# flowloop component: how every flowloop endpoint is registered.
#
# Moonraker registers the endpoint (HTTP and JSON-RPC alike); its HTTP route
# is then served by FlowloopRequestHandler, Moonraker's own handler with two
# differences an HTTP client relies on:
#
# - a refusal's JSON body carries the one line the JSON-RPC client gets.
#   Moonraker copies the body's message from the reason phrase, which tornado
#   replaces by "Unknown" when it holds a `<` (a profile named "PLA <fast>");
#   the reason phrase itself is errors.reason_phrase (`<` as `\x3c`).
# - a JSON body that does not decode is refused as such. Moonraker drops it
#   and the endpoint would see no arguments at all ("the profile is missing").
#   So is one nested deeper than flowloop.nesting.MAX_JSON_DEPTH: decoding
#   it recurses once per level (RecursionError, a 500, at ~1000).
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
import traceback
from typing import TYPE_CHECKING, Any, Optional

import tornado.web

from flowloop.errors import FlowloopError
from flowloop.nesting import check_json_depth

from ...utils import json_wrapper as jsonw
from ..application import DynamicRequestHandler
from .errors import one_line, reason_phrase

if TYPE_CHECKING:
    from ...server import Server


def body_refusal(content_type: str, body: bytes) -> Optional[str]:
    """Why Moonraker would drop this request body, or None (no JSON body, or
    a JSON object: Moonraker's own decoder is the judge)."""
    if not content_type.strip().startswith("application/json") or not body.strip():
        return None
    try:
        check_json_depth(body, "the request body")
        decoded = jsonw.loads(body)
    except FlowloopError as e:
        logging.info(f"flowloop: request refused: {one_line(e)}")
        return str(e)
    except jsonw.JSONDecodeError as e:
        return f"the request body is not valid JSON: {e}"
    if not isinstance(decoded, dict):
        return (f"the request body must be a JSON object of arguments, got "
                f"{type(decoded).__name__}")
    return None


class FlowloopRequestHandler(DynamicRequestHandler):
    def parse_args(self) -> Any:
        refusal = body_refusal(self.request.headers.get("Content-Type", ""),
                               self.request.body)
        if refusal is not None:
            raise tornado.web.HTTPError(400, reason=one_line(refusal))
        return super().parse_args()

    def set_status(self, status_code: int, reason: Optional[str] = None) -> None:
        super().set_status(status_code,
                           None if reason is None else reason_phrase(reason))

    def write_error(self, status_code: int, **kwargs: Any) -> None:
        exc_info = kwargs.get("exc_info")
        error = exc_info[1] if exc_info else None
        # The message before tornado made a reason phrase of it.
        message = getattr(error, "reason", None) or self._reason
        err = {"code": status_code, "message": message}
        if exc_info:  # as Moonraker's handler answers
            err["traceback"] = "\n".join(traceback.format_exception(*exc_info))
        self.set_header("Content-Type", "application/json; charset=UTF-8")
        self.finish(jsonw.dumps({"error": err}))


def register_endpoint(server: Server, path: str, *args: Any, **kwargs: Any) -> None:
    """server.register_endpoint, the HTTP route then served by
    FlowloopRequestHandler."""
    server.register_endpoint(path, *args, **kwargs)
    app = server.lookup_component("application")
    router = getattr(app, "mutable_router", None)
    rules = getattr(router, "pattern_to_rule", {})
    rule = rules.get(f"{getattr(app, 'route_prefix', '')}{path}")
    if rule is None or rule.target is not DynamicRequestHandler:
        # Another Moonraker: its own handler serves (see above).
        logging.info(f"flowloop: {path} is served by Moonraker's own handler")
        return
    rule.target = FlowloopRequestHandler
