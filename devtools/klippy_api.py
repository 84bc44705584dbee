"""A client of klippy's own API socket (JSON messages ended by 0x03), as
Moonraker and Klipper's scripts/motan talk to it: for tests and demos."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path
from typing import Iterator, List, Union

# status_now(): the macro of tests/klippy/status_macro.cfg and the remote
# method it calls
STATUS_MACRO = "_FLOWLOOP_STATUS"
STATUS_METHOD = "flowloop_status"


class KlippyApi:
    """One request at a time with call(); messages that answer no request
    (remote method calls, subscriptions) are kept in `remote`. send() and
    messages() are for streams (dump endpoints)."""

    def __init__(self, path: Union[str, Path], timeout: float = 60.0):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(str(path))
        self.sock.settimeout(timeout)
        self.buffer = b""
        self.next_id = 0
        self.remote: List[dict] = []
        self.status_registered = False

    def send(self, method: str, **params) -> int:
        self.next_id += 1
        self.sock.sendall(json.dumps({"id": self.next_id, "method": method,
                                      "params": params}).encode() + b"\x03")
        return self.next_id

    def _next_message(self) -> dict:
        while b"\x03" not in self.buffer:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("klippy closed its API socket")
            self.buffer += chunk
        raw, self.buffer = self.buffer.split(b"\x03", 1)
        return json.loads(raw)

    def call(self, method: str, **params):
        """The result of one request; its error as RuntimeError(message)."""
        request = self.send(method, **params)
        while True:
            msg = self._next_message()
            if msg.get("id") == request:
                if "error" in msg:
                    raise RuntimeError(msg["error"]["message"])
                return msg["result"]
            if "id" not in msg:
                self.remote.append(msg)

    def messages(self, seconds: float) -> Iterator[dict]:
        """Every message that arrives within `seconds` (the socket's timeout
        is the polling interval)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                yield self._next_message()
            except socket.timeout:
                continue
            except ConnectionError:
                return

    def gcode(self, script: str):
        return self.call("gcode/script", script=script)

    def query(self, obj: str) -> dict:
        return self.query_many(obj)[obj]

    def query_many(self, *objects: str) -> dict:
        """{object: its status} in one request. Ask for what you need at
        once: klippy answers a query on its status timer's next tick, up to
        0.25 s after the last one, so each request in a loop costs that."""
        return self.call("objects/query",
                         objects={obj: None for obj in objects})["status"]

    def status_now(self, *objects: str) -> dict:
        """{object: its status} at once, as query_many() would give it
        without waiting for klippy's status tick: the macro of
        tests/klippy/status_macro.cfg (which the printer's config must
        include) sends it through a remote method this client registers.
        For loops that read status after every chunk of G-code."""
        if not self.status_registered:
            self.call("register_remote_method", remote_method=STATUS_METHOD,
                      response_template={"method": STATUS_METHOD})
            self.status_registered = True
        self.gcode(f'{STATUS_MACRO} OBJECTS="{",".join(objects)}"')
        # sent while the script ran, so before its result
        for i, msg in enumerate(self.remote):
            if msg.get("method") == STATUS_METHOD:
                del self.remote[i]
                return msg["params"]["status"]
        raise RuntimeError(f"{STATUS_MACRO} sent no status: is"
                           " tests/klippy/status_macro.cfg included?")

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> KlippyApi:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
