"""A throw-away PostgreSQL server for the tests that run Spoolman on it, from
Debian's `postgresql` (`initdb`, `pg_ctl`; `.ci/run` installs it): a fresh
cluster in a temporary folder, trust authentication, listening on
127.0.0.1 and a socket in that folder only, stopped and deleted after.

initdb refuses to run as root: as root the cluster belongs to the
`postgres` user Debian's package creates (run through `runuser`)."""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import subprocess
from pathlib import Path
from typing import Dict, Iterator, List, Optional

from devtools import stack

USER = "flowloop"
DATABASE = "spoolman"


def _tool(name: str) -> Optional[str]:
    found = shutil.which(name)
    if found:
        return found
    versions = sorted(Path("/usr/lib/postgresql").glob(f"*/bin/{name}"))
    return str(versions[-1]) if versions else None


def _owner() -> Optional[str]:
    """Who runs the cluster: us, or as root Debian's postgres user."""
    if os.getuid() != 0:
        return pwd.getpwuid(os.getuid()).pw_name
    try:
        pwd.getpwnam("postgres")
    except KeyError:
        return None
    return "postgres" if shutil.which("runuser") else None


def missing_postgres_reason() -> Optional[str]:
    if not (_tool("initdb") and _tool("pg_ctl") and shutil.which("psql")):
        return ("no PostgreSQL server here (Debian's postgresql: initdb, pg_ctl,"
                " psql): the Spoolman-on-PostgreSQL run is SKIPPED")
    if _owner() is None:
        return ("running as root without Debian's postgres user (initdb refuses"
                " root): the Spoolman-on-PostgreSQL run is SKIPPED")
    return None


def _as_owner(cmd: List[str], owner: str) -> List[str]:
    if os.getuid() == 0:
        return ["runuser", "-u", owner, "--", *cmd]
    return cmd


@contextlib.contextmanager
def postgres() -> Iterator[Dict[str, str]]:
    """Spoolman's SPOOLMAN_DB_* settings for a running server with an empty
    database; stopped and deleted on leaving."""
    owner = _owner()
    assert owner is not None, missing_postgres_reason()
    root = stack.short_tempdir("fl-pg-")
    data, sockets = root / "data", root / "run"
    sockets.mkdir()
    if os.getuid() == 0:
        shutil.chown(root, owner)
        shutil.chown(sockets, owner)
    port = stack.free_port()
    started = False
    try:
        stack._run(_as_owner([_tool("initdb"), "-D", str(data), "-A", "trust",
                              "-U", USER, "--no-sync"], owner))
        stack._run(_as_owner(
            [_tool("pg_ctl"), "-D", str(data), "-l", str(root / "server.log"),
             "-w", "-o", f"-p {port} -h 127.0.0.1 -k {sockets} -F", "start"],
            owner))
        started = True
        subprocess.run(["psql", "-h", "127.0.0.1", "-p", str(port), "-U", USER,
                        "-d", "postgres", "-q", "-c",
                        f"CREATE DATABASE {DATABASE}"], check=True,
                       capture_output=True)
        yield {"SPOOLMAN_DB_TYPE": "postgres", "SPOOLMAN_DB_HOST": "127.0.0.1",
               "SPOOLMAN_DB_PORT": str(port), "SPOOLMAN_DB_NAME": DATABASE,
               "SPOOLMAN_DB_USERNAME": USER, "SPOOLMAN_DB_PASSWORD": "unused"}
    finally:
        if started:
            subprocess.run(_as_owner([_tool("pg_ctl"), "-D", str(data), "-m",
                                      "immediate", "-w", "stop"], owner),
                           capture_output=True)
        shutil.rmtree(root, ignore_errors=True)
