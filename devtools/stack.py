"""The real hosts for tests and the demo: a patched Klipper build, the host
virtualenvs, and klippy/Moonraker processes on loopback.

- The user's Klipper checkout (KLIPPER_PATH, default ~/klipper) is copied into
  a cache keyed by its commit, its local changes and flowloop's patch inputs,
  patched with flowloop.host.install (the code `flowloop install` runs), and
  Klipper's own `make` builds the MCU data dictionaries for the targets below.
- Host virtualenvs are built as users build them: the host's pinned
  requirements first, then flowloop; the freeze before and after is kept so a
  test can prove nothing pinned moved.
- Every process started here is stopped by its pid.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Type
from urllib.parse import quote

PROJECT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(PROJECT))

from devtools.klippy_api import KlippyApi  # noqa: E402
from flowloop.host import install  # noqa: E402

TARGETS = ("linuxprocess", "atmega2560")
MOONRAKER_REQUIREMENT = "moonraker==0.11.0"


# The hosts the klippy tier runs on: Klipper, and Kalico (the Klipper fork
# with MPC and plugins), each from its own checkout. FLOWLOOP_HOSTS=klipper
# narrows a run to one (`make test-quick` does); `make test` runs both.
ALL_HOSTS = ("klipper", "kalico")


def _hosts() -> tuple:
    asked = tuple(os.environ.get("FLOWLOOP_HOSTS", " ".join(ALL_HOSTS)).split())
    unknown = [h for h in asked if h not in ALL_HOSTS]
    if unknown or not asked:
        raise SystemExit(f"FLOWLOOP_HOSTS: {' '.join(unknown) or 'empty'} is not "
                         f"one of {', '.join(ALL_HOSTS)}")
    return asked


HOSTS = _hosts()
HOST_PATH_VARIABLES = {"klipper": "KLIPPER_PATH", "kalico": "KALICO_PATH"}
HOST_URLS = {"klipper": "https://github.com/Klipper3d/klipper",
             "kalico": "https://github.com/KalicoCrew/kalico"}


def klipper_path(host: str = "klipper") -> Path:
    """The user's checkout of host: $KLIPPER_PATH or ~/klipper, $KALICO_PATH
    or ~/kalico."""
    return Path(os.environ.get(HOST_PATH_VARIABLES[host], f"~/{host}")).expanduser()


def cache_dir() -> Path:
    base = os.environ.get("FLOWLOOP_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", "~/.cache"), "flowloop")
    path = Path(base).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    return path


def cache_bytecode() -> Path:
    """Let this process and every Python the tests start keep compiled
    bytecode, in the cache instead of beside the sources.

    With PYTHONDONTWRITEBYTECODE set (as on CI's machines) every klippy,
    Moonraker and test worker compiled each module it imported on every
    start, and pytest rewrote every test module's asserts again in each
    worker: about a third of a batch-mode klippy test's CPU. A
    PYTHONPYCACHEPREFIX tree writes nothing into a source tree, so the
    user's Klipper, Kalico and Moonraker checkouts stay as they were (and a
    Python without the variable would have written __pycache__ there)."""
    prefix = cache_dir() / "pycache"
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    os.environ["PYTHONPYCACHEPREFIX"] = str(prefix)
    sys.dont_write_bytecode = False
    sys.pycache_prefix = str(prefix)
    return prefix


def missing_klipper_reason(host: str = "klipper") -> Optional[str]:
    path = klipper_path(host)
    variable = HOST_PATH_VARIABLES[host]
    try:
        install.check_klipper_tree(path)
        if host == "kalico" and not install.is_kalico(path):
            raise install.InstallError(f"{path} is not a Kalico tree (no "
                                       f"klippy/plugins/)")
    except install.InstallError as e:
        if host == "kalico":
            return (f"no Kalico checkout at {path} ({e}): the klippy tier's Kalico "
                    f"runs are SKIPPED. Get one with 'git clone {HOST_URLS[host]} "
                    f"~/kalico' or set {variable}.")
        return (f"no Klipper checkout at {path} ({e}): the klippy tier and the klippy "
                f"half of the moonraker tier are SKIPPED. Get one with "
                f"'git clone {HOST_URLS[host]} ~/klipper' "
                f"or set {variable}.")
    return None


def log(msg: str) -> None:
    print(f"[flowloop stack] {msg}", file=sys.stderr, flush=True)


def _run(cmd: List[str], cwd: Optional[Path] = None, log_file: Optional[Path] = None,
         **kw) -> str:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, **kw)
    if log_file is not None:  # kept so tests can check the build for warnings
        log_file.write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n"
                           f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc.stdout


def _hash_files(h, root: Path, paths: List[Path]) -> None:
    for path in paths:
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes() if path.is_file() else b"dir")


@contextlib.contextmanager
def _locked(name: str) -> Iterator[None]:
    with open(cache_dir() / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _prune(candidates, keep: Path, newest: int = 2) -> None:
    """Drop stale builds, sparing the newest few (another run may still use
    them: each use makes a build newest, build_klipper; a second checkout's
    run once pruned the build a running make test used, as the last use
    did not count)."""
    old = sorted((p for p in candidates if p.is_dir() and p != keep),
                 key=lambda p: p.stat().st_mtime, reverse=True)
    for path in old[newest:]:
        shutil.rmtree(path, ignore_errors=True)


class KlipperBuild:
    """A patched copy of the user's Klipper (or Kalico) with MCU dictionaries
    built."""

    def __init__(self, tree: Path, host: str = "klipper"):
        self.tree = tree
        self.host = host
        self.dict_dir = tree / "flowloop-dict"

    @property
    def klippy(self) -> Path:
        return self.tree / "klippy" / "klippy.py"

    def dictionary(self, target: str) -> Path:
        return self.dict_dir / f"{target}.dict"

    def elf(self, target: str) -> Path:
        return self.dict_dir / f"{target}.elf"


def klipper_key(source: Path = PROJECT, host: str = "klipper") -> str:
    kp = klipper_path(host)
    h = hashlib.sha256()
    # read only, and no index refresh: `git status` would otherwise write
    # the user's index (index.lock) while another process copies the .git
    git = ["git", "--no-optional-locks", "-C", str(kp)]
    h.update(_run([*git, "rev-parse", "HEAD"]).encode())
    h.update(_run([*git, "status", "--porcelain"]).encode())
    h.update(_run([*git, "diff"]).encode())
    h.update(str(source).encode())  # the symlinks point into this checkout
    h.update(b"firmware patch taken out after the build")  # trees before: stale
    _hash_files(h, source,
                [source / "flowloop" / "host" / "install.py"]
                + install.mcu_sources(source))
    # klippy modules are links: their names shape the tree, their text does not.
    h.update(" ".join(p.name for p in install.klippy_modules(source)).encode())
    return h.hexdigest()[:16]


def build_klipper(source: Path = PROJECT, targets=TARGETS,
                  host: str = "klipper") -> KlipperBuild:
    key = klipper_key(source, host)
    tree = cache_dir() / f"{host}-{key}"
    build = KlipperBuild(tree, host)
    with _locked(host):
        if (tree / ".flowloop-ready").exists():
            # a build in use is a recent one: _prune spares the newest
            os.utime(tree)
            return build
        log(f"copying {klipper_path(host)} to {tree} and patching it")
        tmp = tree.with_name(tree.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        skip = shutil.ignore_patterns("out", ".config", "*.pyc", "__pycache__")
        link_lib = host == "kalico"  # its lib/ (vendored MCU SDKs) is 200 MB

        def ignore(folder, names):
            top = link_lib and Path(folder) == klipper_path(host)
            return set(skip(folder, names)) | ({"lib"} if top else set())
        shutil.copytree(klipper_path(host), tmp, symlinks=True, ignore=ignore)
        if link_lib:
            (tmp / "lib").symlink_to(klipper_path(host) / "lib")
        # what `flowloop install` links, then the EMS22 patch `flowloop
        # firmware` makes in its own copy (the MCU code is built from both)
        install.apply(install.plan_klipper(tmp, source))
        install.apply(install.plan_firmware(tmp, source))
        dict_dir = tmp / "flowloop-dict"
        dict_dir.mkdir()
        for target in targets:
            log(f"building {host}'s MCU code for {target}")
            _run(["make", "distclean"], cwd=tmp)
            shutil.copy(tmp / "test" / "configs" / f"{target}.config", tmp / ".config")
            _run(["make", "olddefconfig"], cwd=tmp)
            _run(["make", f"-j{os.cpu_count() or 2}"], cwd=tmp,
                 log_file=dict_dir / f"{target}.log")
            shutil.copy(tmp / "out" / "klipper.dict", dict_dir / f"{target}.dict")
            shutil.copy(tmp / "out" / "klipper.elf", dict_dir / f"{target}.elf")
            shutil.copy(tmp / ".config", dict_dir / f"{target}.config")
        _run(["make", "distclean"], cwd=tmp)
        # klippy runs from the tree as a user's checkout is after `flowloop
        # install`: the EMS22 patch lives only in flowloop firmware's copy
        install.apply(install.plan_firmware(tmp, source, uninstall=True))
        _prune(cache_dir().glob(f"{host}-[0-9a-f]*"), keep=tmp)
        tmp.rename(tree)
        (tree / ".flowloop-ready").write_text(key)
    return build


class Venv:
    def __init__(self, path: Path):
        self.path = path
        self.python = path / "bin" / "python"

    def freeze(self, which: str) -> Dict[str, str]:
        return json.loads((self.path / f"freeze-{which}.json").read_text())

    def moved_by_flowloop(self) -> Dict[str, tuple]:
        """Host packages installing flowloop changed: {name: (was, is)}."""
        host, after = self.freeze("host"), self.freeze("flowloop")
        return {name: (was, after.get(name)) for name, was in host.items()
                if after.get(name) != was}


def _freeze(python: Path) -> Dict[str, str]:
    out = _run([str(python), "-m", "pip", "list", "--format=json",
                "--disable-pip-version-check"])
    return {p["name"].lower(): p["version"] for p in json.loads(out)}


def _install_metadata() -> bytes:
    """What of pyproject.toml shapes an installed flowloop: its build system
    and [project] (dependencies, extras, scripts), not the tools' settings
    (pytest's markers, ruff's rules), whose edits need no new virtualenv."""
    text = (PROJECT / "pyproject.toml").read_bytes()
    try:
        import tomllib
    except ImportError:  # Python < 3.11: the whole file
        return text
    data = tomllib.loads(text.decode())
    return json.dumps({key: data.get(key) for key in ("build-system", "project")},
                      sort_keys=True).encode()


def _build_venv(name: str, host_install: List[str], extra: str,
                key_parts: List[bytes]) -> Venv:
    h = hashlib.sha256()
    for part in key_parts + [str(PROJECT).encode(), _install_metadata(),
                             sys.version.encode()]:
        h.update(part)
    path = cache_dir() / f"{name}-{h.hexdigest()[:16]}"
    venv = Venv(path)
    with _locked(name):
        if (path / ".flowloop-ready").exists():
            return venv
        log(f"building {name} virtualenv: host requirements, then flowloop")
        shutil.rmtree(path, ignore_errors=True)
        _run([sys.executable, "-m", "venv", str(path)])
        pip = [str(venv.python), "-m", "pip", "install", "-q",
               "--disable-pip-version-check"]
        _run(pip + host_install)
        (path / "freeze-host.json").write_text(json.dumps(_freeze(venv.python)))
        _run(pip + ["-e", f"{PROJECT}{extra}"])
        (path / "freeze-flowloop.json").write_text(json.dumps(_freeze(venv.python)))
        _prune(cache_dir().glob(f"{name}-*"), keep=path)
        (path / ".flowloop-ready").write_text("ok")
    return venv


def klippy_venv(host: str = "klipper") -> Venv:
    reqs = klipper_path(host) / "scripts" / "klippy-requirements.txt"
    name = "klippy-venv" if host == "klipper" else f"{host}-venv"
    return _build_venv(name, ["-r", str(reqs)], "", [reqs.read_bytes()])


def moonraker_venv() -> Venv:
    venv = _build_venv("moonraker-venv", [MOONRAKER_REQUIREMENT], "[moonraker]",
                       [MOONRAKER_REQUIREMENT.encode()])
    # Install the component exactly as `flowloop install` does (idempotent;
    # locked: pytest's workers each ask for the venv).
    with _locked("moonraker-venv"):
        install.apply(install.plan_moonraker(venv.path, PROJECT))
    return venv


# ---------------------------------------------------------------------------
# Moonraker as KIAUH installs it: a git checkout, run from its source


MOONRAKER_URL = "https://github.com/Arksine/moonraker"


def moonraker_checkout_path() -> Path:
    """The user's Moonraker checkout: $MOONRAKER_PATH or ~/moonraker."""
    return Path(os.environ.get("MOONRAKER_PATH", "~/moonraker")).expanduser()


def missing_moonraker_checkout_reason() -> Optional[str]:
    path = moonraker_checkout_path()
    if not (path / "moonraker" / "moonraker.py").is_file() \
            or not (path / "scripts" / "moonraker-requirements.txt").is_file():
        return (f"no Moonraker checkout at {path}: the moonraker tier's runs on a"
                f" git checkout (tests/moonraker/test_moonraker_checkout.py) are"
                f" SKIPPED. Get one with 'git clone {MOONRAKER_URL} ~/moonraker'"
                f" or set MOONRAKER_PATH.")
    return None


class MoonrakerCheckout:
    """A copy of the user's Moonraker checkout (its .git too, so its update
    manager sees a checkout) with flowloop installed as `flowloop install`
    installs it into a checkout, and a virtualenv of the checkout's own
    requirements plus flowloop."""

    def __init__(self, tree: Path, venv: Venv):
        self.tree = tree
        self.venv = venv

    @property
    def script(self) -> Path:
        """What KIAUH's moonraker.service runs."""
        return self.tree / "moonraker" / "moonraker.py"


def moonraker_checkout() -> MoonrakerCheckout:
    source = moonraker_checkout_path()
    h = hashlib.sha256()
    for args in (["rev-parse", "HEAD"], ["status", "--porcelain"], ["diff"]):
        h.update(_run(["git", "-C", str(source), *args]).encode())
    h.update(str(PROJECT).encode())
    h.update(" ".join(p.name for p in install.moonraker_components(PROJECT)).encode())
    tree = cache_dir() / f"moonraker-checkout-{h.hexdigest()[:16]}"
    # the mark is beside the tree: in it, git would see an untracked file
    ready = tree.with_name(tree.name + ".ready")
    with _locked("moonraker-checkout"):
        if not ready.exists() or not tree.is_dir():
            log(f"copying {source} to {tree}, flowloop installed into the copy")
            tmp = tree.with_name(tree.name + ".tmp")
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(source, tmp, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            _prune(cache_dir().glob("moonraker-checkout-[0-9a-f]*"), keep=tmp)
            shutil.rmtree(tree, ignore_errors=True)
            tmp.rename(tree)
            ready.write_text("ok")
        # the links point at this checkout: made (idempotently) on every use
        install.apply(install.plan_moonraker(tree, PROJECT))
    reqs = source / "scripts" / "moonraker-requirements.txt"
    venv = _build_venv("moonraker-checkout-venv", ["-r", str(reqs)],
                       "[moonraker]", [reqs.read_bytes()])
    return MoonrakerCheckout(tree, venv)


# ---------------------------------------------------------------------------
# Processes


def wait_until(predicate, timeout: float, interval: float = 0.1):
    """Poll predicate() until it returns something true; return that, or the
    last (false) value at the timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    return predicate()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def accepts(unix_socket: Path) -> bool:
    """A server listens on unix_socket (its file appears at bind(), a moment
    before listen(): a connect between the two is refused)."""
    if not unix_socket.exists():
        return False
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(str(unix_socket))
        except OSError:
            return False
    return True


def short_tempdir(prefix: str) -> Path:
    # Unix socket paths must stay under ~100 bytes: keep these out of pytest's tmp.
    return Path(tempfile.mkdtemp(prefix=prefix, dir="/tmp"))


class Process:
    def __init__(self, name: str, cmd: List[str], log_path: Path, **kw):
        self.name = name
        self.log_path = log_path
        self._out = open(log_path.with_suffix(".stdout"), "wb")
        # Own session: a terminal's Ctrl-C reaches only the supervisor, which
        # stops each child by pid (Moonraker hit by SIGINT hangs on SIGTERM).
        self.proc = subprocess.Popen(cmd, stdout=self._out, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL,
                                     start_new_session=True, **kw)
        self.pid = self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> None:
        if self.proc.poll() is None:
            os.kill(self.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.kill(self.pid, signal.SIGKILL)
                self.proc.wait()
        self._out.close()

    def log_tail(self, chars: int = 4000) -> str:
        text = ""
        for path in (self.log_path, self.log_path.with_suffix(".stdout")):
            if path.exists():
                text += f"--- {path}\n" + path.read_text(errors="replace")[-chars:]
        return text


REALTIME_KLIPPY = PROJECT / "devtools" / "realtime_klippy.py"


def build_chelper(build: KlipperBuild, venv: Venv) -> None:
    """Compile klippy's C helper into the build, once: klippy does it on
    first use, and two klippy processes starting at once on a fresh build
    race on renaming the result (the second fails: FileNotFoundError on
    _temp_c_helper.so). Later calls find it built and return at once (the
    build's C sources never change: a new patch is a new build)."""
    if (build.tree / "klippy" / "chelper" / "c_helper.so").exists():
        return
    with _locked(f"{build.host}-chelper"):
        _run([str(venv.python), "-c", "import chelper; chelper.get_ffi()"],
             cwd=build.tree / "klippy")


class Klippy(Process):
    """klippy in batch mode (MCU output to a file) with an API socket and a pty.

    realtime: run it through devtools/realtime_klippy.py, print time paced to
    the clock (G-code executes in real time, the toolhead holds the reader
    1-2 s ahead, a simulated flow sensor samples as time passes)."""

    def __init__(self, build: KlipperBuild, venv: Venv, config: Path, workdir: Path,
                 dictionaries: Optional[Dict[str, str]] = None,
                 api_socket: Optional[Path] = None, realtime: bool = False):
        self.workdir = workdir
        self.api_socket = api_socket or workdir / "klippy.sock"
        self.pty = workdir / "printer"
        build_chelper(build, venv)
        self.realtime = realtime
        dictionaries = dictionaries or {"mcu": "linuxprocess"}
        launcher = [str(REALTIME_KLIPPY)] if realtime else []
        cmd = [str(venv.python)] + launcher + [str(build.klippy), str(config),
               "-a", str(self.api_socket), "-I", str(self.pty),
               "-o", str(workdir / "mcu-output"), "-l", str(workdir / "klippy.log")]
        for mcu, target in dictionaries.items():
            path = build.dictionary(target)
            cmd += ["-d", str(path) if mcu == "mcu" else f"{mcu}={path}"]
        super().__init__("klippy", cmd, workdir / "klippy.log", cwd=str(build.tree))

    def wait_ready(self, timeout: float = 30.0) -> None:
        """Until klippy accepts a connection on its API socket: the file
        appears at bind(), a moment before listen() (a connect between the
        two is refused; on a loaded machine the moment grows)."""
        if not wait_until(lambda: accepts(self.api_socket) or not self.alive(),
                          timeout) or not self.alive():
            raise RuntimeError("klippy did not open its API socket:\n"
                               + self.log_tail())

    def ready_api(self, timeout: float = 30.0,
                  api_class: Type[KlippyApi] = KlippyApi) -> KlippyApi:
        """A connection to klippy's API once klippy says it is ready (its
        configuration read, its MCU connected): the socket open (wait_ready),
        then the state 'ready'; RuntimeError with klippy's own message and
        the log's tail if not within timeout, or at once where klippy
        stopped in 'error' or 'shutdown' (a config error: it never gets
        ready). api_class: a KlippyApi of the caller's (one that answers
        remote methods)."""
        self.wait_ready(timeout)
        api = api_class(self.api_socket)
        info = {}

        def settled() -> bool:
            info.update(api.call("info"))
            return info["state"] in ("ready", "error", "shutdown")

        if not wait_until(settled, timeout) or info["state"] != "ready":
            api.close()
            raise RuntimeError(
                f"klippy is not ready ({info.get('state')}):"
                f" {info.get('state_message', '').strip()}\n" + self.log_tail())
        return api


MOONRAKER_CONF = """\
[server]
host: 127.0.0.1
port: {port}
klippy_uds_address: {klippy_uds}

[authorization]
trusted_clients:
    {trusted}
cors_domains:
    *

[machine]
provider: none
validate_service: False
validate_config: False

# Off the network: no Moonlight feed (and misc/usb.ids exists, see Moonraker).
[announcements]
enable_moonlight: False

[flowloop]
{extra}
"""


class Moonraker(Process):
    def __init__(self, venv: Venv, data_dir: Path, klippy_uds: Optional[Path] = None,
                 extra_conf: str = "", port: Optional[int] = None,
                 trusted: str = "127.0.0.0/8", moonraker_path: Optional[Path] = None,
                 cwd: Optional[Path] = None, script: Optional[Path] = None):
        """moonraker_path: a folder holding a `moonraker` package to run instead
        of the venv's own (put first on PYTHONPATH; the venv still gives its
        dependencies). cwd: the working directory it is started in (`python
        -m moonraker` puts it first on sys.path; None: this process's).
        script: a checkout's moonraker/moonraker.py to run with the venv's
        python, as KIAUH's service runs it, instead of `-m moonraker`."""
        self.port = port or free_port()
        self.data_dir = data_dir
        config_dir = data_dir / "config"
        config_dir.mkdir(parents=True, exist_ok=True)
        usb_ids = data_dir / "misc" / "usb.ids"  # present: never downloaded
        usb_ids.parent.mkdir(exist_ok=True)
        usb_ids.touch()
        # Written on every start: a data directory kept from an earlier run
        # (make demo with FLOWLOOP_DEMO_DATA) would otherwise name that run's
        # port and sockets, and this Moonraker would listen where no one asks.
        (config_dir / "moonraker.conf").write_text(MOONRAKER_CONF.format(
            port=self.port,
            klippy_uds=klippy_uds or data_dir / "comms" / "none.sock",
            trusted=trusted, extra=extra_conf))
        run = [str(script)] if script is not None else ["-m", "moonraker"]
        cmd = [str(venv.python), *run, "-d", str(data_dir),
               "-l", str(data_dir / "moonraker.log")]
        env = None
        if moonraker_path is not None:
            env = {**os.environ, "PYTHONPATH": str(moonraker_path)}
        super().__init__("moonraker", cmd, data_dir / "moonraker.log", env=env,
                         cwd=cwd)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def request(self, method: str, path: str, body=None, timeout: float = 10.0,
                headers: Optional[Dict[str, str]] = None):
        """(status, decoded JSON or text) of one HTTP request."""
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method,
                                     headers={"Content-Type": "application/json",
                                              **(headers or {})})
        try:
            with urllib.request.urlopen(req, timeout=timeout) as resp:
                status, raw = resp.status, resp.read()
                ctype = resp.headers.get("Content-Type", "")
        except urllib.error.HTTPError as e:
            status, raw, ctype = e.code, e.read(), e.headers.get("Content-Type", "")
        text = raw.decode(errors="replace")
        return status, (json.loads(text) if "json" in ctype else text)

    def upload(self, name: str, data: bytes, timeout: float = 120.0) -> dict:
        """POST /server/files/upload (multipart, as a browser sends it): the
        decoded answer (Moonraker waits for its file processors first)."""
        boundary = uuid.uuid4().hex
        body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\";"
                f" filename=\"{name}\"\r\nContent-Type: application/octet-stream"
                f"\r\n\r\n").encode() + data + f"\r\n--{boundary}--\r\n".encode()
        req = urllib.request.Request(
            self.url + "/server/files/upload", data=body, method="POST",
            headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return json.loads(resp.read())

    def _ready(self, klippy: bool) -> bool:
        try:
            status, body = self.request("GET", "/server/info", timeout=2)
        except (OSError, ValueError):
            return False
        if status == 401:
            return not klippy  # up, but this client is not in trusted_clients
        return status == 200 and (not klippy
                                  or (body["result"]["klippy_state"] == "ready"
                                      and self._klippy_initialized()))

    def _klippy_initialized(self) -> bool:
        """Moonraker has run its klippy-ready handlers since it started: it
        says klippy_state "ready" before that, and a job started in between
        is seen by none of its components (no history, no flow report)."""
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return False
        return "Klippy ready" in text[text.rfind("Starting Moonraker"):]

    def wait_ready(self, timeout: float = 60.0, klippy: bool = False) -> None:
        if not wait_until(lambda: self._ready(klippy) or not self.alive(), timeout,
                          interval=0.2) or not self.alive():
            raise RuntimeError("moonraker not ready:\n" + self.log_tail())


class PrinterStack:
    """klippy (batch mode, optional) + Moonraker laid out like ~/printer_data."""

    def __init__(self, data_dir: Path, moonraker: Moonraker,
                 klippy: Optional[Klippy]):
        self.data_dir = data_dir
        self.moonraker = moonraker
        self.klippy = klippy

    def gcode(self, script: str) -> str:
        status, body = self.moonraker.request("POST", "/printer/gcode/script",
                                              {"script": script}, timeout=120)
        if status != 200:
            raise RuntimeError(f"G-code {script!r} failed: {body}")
        return body["result"]

    def query(self, obj: str) -> dict:
        return self.query_many(obj)[obj]

    def query_many(self, *objects: str) -> dict:
        """{object: its status} in one request: klippy answers a query on
        its status timer's next tick, up to 0.25 s after the last one, so
        each request in a loop costs that (an object klippy lacks: {})."""
        status, body = self.moonraker.request(
            "GET", "/printer/objects/query?" + "&".join(quote(o) for o in objects))
        if status != 200:
            raise RuntimeError(f"query {objects!r} failed: {body}")
        found = body["result"]["status"]
        return {obj: found.get(obj, {}) for obj in objects}


@contextlib.contextmanager
def printer_stack(printer_cfg: Optional[Path] = None, with_klippy: bool = True,
                  moonraker_conf: str = "", trusted: str = "127.0.0.0/8",
                  target: str = "atmega2560",
                  data_dir: Optional[Path] = None,
                  build: Optional[KlipperBuild] = None,
                  klippy_ready: bool = True,
                  realtime: bool = False) -> Iterator[PrinterStack]:
    """Start Moonraker (and klippy with printer_cfg, default config/printer.cfg).

    The printer config in data_dir/config/printer.cfg includes the given file
    and points virtual_sdcard at data_dir/gcodes, as Moonraker expects. A
    data_dir given is kept (and may be one an earlier stack used: its
    database and G-code files carry over, its config files are rewritten);
    without one, a temporary directory is used and removed. build: a Klipper
    tree to run instead of build_klipper()'s; klippy_ready=False only waits
    for Moonraker (a broken printer's klippy never gets ready). realtime:
    klippy's print time follows the clock (see Klippy), for live views.
    """
    own_dir = data_dir is None
    data_dir = data_dir or short_tempdir("fl-stack-")
    for sub in ("config", "gcodes", "comms", "logs"):
        (data_dir / sub).mkdir(parents=True, exist_ok=True)
    klippy = moonraker = None
    try:
        uds = data_dir / "comms" / "klippy.sock"
        if uds.is_socket():  # left by an earlier run: not a sign klippy is up
            uds.unlink()
        if with_klippy:
            cfg = data_dir / "config" / "printer.cfg"
            include = printer_cfg or PROJECT / "config" / "printer.cfg"
            cfg.write_text(f"[include {include}]\n\n[virtual_sdcard]\n"
                           f"path: {data_dir / 'gcodes'}\n")
            klippy = Klippy(build or build_klipper(), klippy_venv(), cfg,
                            data_dir / "logs",
                            {"mcu": target}, api_socket=uds, realtime=realtime)
        moonraker = Moonraker(moonraker_venv(), data_dir,
                              klippy_uds=klippy.api_socket if klippy else None,
                              extra_conf=moonraker_conf, trusted=trusted)
        if klippy:
            klippy.wait_ready()
        moonraker.wait_ready(klippy=klippy is not None and klippy_ready)
        yield PrinterStack(data_dir, moonraker, klippy)
    finally:
        for proc in (moonraker, klippy):
            if proc is not None:
                proc.stop()
        if own_dir:
            shutil.rmtree(data_dir, ignore_errors=True)
