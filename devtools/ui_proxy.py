"""A built Mainsail or Fluidd and Moonraker on one origin, as the usual nginx
configuration of both UIs serves them (KIAUH, MainsailOS): the UI's files
with index.html for any other path (try_files $uri $uri/ /index.html), and
/websocket and /(printer|api|access|machine|server)/ passed to Moonraker.
Relative links in what Moonraker gives the UI resolve here as they do behind
that nginx.

python -m devtools.ui_proxy PORT DIST MOONRAKER_PORT [CONFIG_JSON]
CONFIG_JSON: served as /config.json instead of dist's.
"""

from __future__ import annotations

import asyncio
import re
import sys
from pathlib import Path

from tornado import httpclient, web, websocket

API = re.compile(r"^/(?:printer|api|access|machine|server)/")
HOP_BY_HOP = {"connection", "keep-alive", "transfer-encoding", "content-length",
              "content-encoding", "upgrade", "host"}


class Proxy(web.RequestHandler):
    upstream = ""

    async def _pass(self) -> None:
        headers = {k: v for k, v in self.request.headers.get_all()
                   if k.lower() not in HOP_BY_HOP}
        body = self.request.body if self.request.method in ("POST", "PUT",
                                                            "PATCH") else None
        request = httpclient.HTTPRequest(
            self.upstream + self.request.uri, method=self.request.method,
            headers=headers, body=body, allow_nonstandard_methods=True,
            follow_redirects=False, request_timeout=120)
        resp = await httpclient.AsyncHTTPClient().fetch(request, raise_error=False)
        if resp.code == 599:
            raise web.HTTPError(502)
        self.set_status(resp.code, resp.reason)
        for k, v in resp.headers.get_all():
            if k.lower() not in HOP_BY_HOP:
                self.add_header(k, v)
        if resp.body:
            self.write(resp.body)

    get = post = delete = put = patch = _pass


class SocketProxy(websocket.WebSocketHandler):
    upstream = ""

    def check_origin(self, origin: str) -> bool:
        return True

    async def open(self) -> None:
        self.pending = []
        self.up = None
        self.up = await websocket.websocket_connect(
            self.upstream, on_message_callback=self._from_upstream)
        for msg in self.pending:
            await self.up.write_message(msg)

    def _from_upstream(self, msg) -> None:
        if msg is None:
            self.close()
        elif self.ws_connection is not None:
            self.write_message(msg)

    async def on_message(self, message) -> None:
        if self.up is None:
            self.pending.append(message)
        else:
            await self.up.write_message(message)

    def on_close(self) -> None:
        if self.up is not None:
            self.up.close()


class Files(web.StaticFileHandler):
    """try_files $uri $uri/ /index.html"""

    def validate_absolute_path(self, root: str, absolute_path: str):
        if not Path(absolute_path).is_file():
            absolute_path = str(Path(root) / "index.html")
        return super().validate_absolute_path(root, absolute_path)

    def set_extra_headers(self, path: str) -> None:
        self.set_header("Cache-Control", "no-store")


def app(dist: Path, moonraker_port: int, config_json: Path = None) -> web.Application:
    Proxy.upstream = f"http://127.0.0.1:{moonraker_port}"
    SocketProxy.upstream = f"ws://127.0.0.1:{moonraker_port}/websocket"
    routes = [(r"/websocket", SocketProxy), (API.pattern + ".*", Proxy)]
    if config_json is not None:
        routes.append((r"/(config\.json)", web.StaticFileHandler,
                       {"path": str(config_json.parent),
                        "default_filename": config_json.name}))
    routes.append((r"/(.*)", Files, {"path": str(dist),
                                     "default_filename": "index.html"}))
    return web.Application(routes)


async def main(argv) -> None:
    port, dist, moonraker_port = int(argv[0]), Path(argv[1]), int(argv[2])
    config_json = Path(argv[3]) if len(argv) > 3 else None
    server = app(dist, moonraker_port, config_json).listen(port, "127.0.0.1")
    print(f"serving {dist} on 127.0.0.1:{port}", flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        server.stop()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1:]))
