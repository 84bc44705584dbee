"""Firmware in the loop: the patched Klipper's atmega2560 firmware on simavr.

simavr (>= 1.8) comes from its source, as Klipper does: a checkout at
SIMAVR_PATH (default ~/simavr; `git clone https://github.com/buserror/simavr`).
It is built once into flowloop's cache, keyed on its commit, and
fil_harness.c is linked statically against its libsimavr.a. The harness runs
klipper.elf paced to the wall clock, with USART0 on a pty that klippy opens
in normal mode, and a control socket for the models' grip and faults.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from devtools import stack

HERE = Path(__file__).resolve().parent
HARNESS_SOURCE = HERE / "fil_harness.c"
RUNNER_SOURCE = HERE / "run_program.c"
SIMAVR_URL = "https://github.com/buserror/simavr"
MIN_VERSION = (1, 8)


def simavr_path() -> Path:
    return Path(os.environ.get("SIMAVR_PATH", "~/simavr")).expanduser()


def _git(path: Path, *args: str) -> str:
    # read only: never write the user's checkout (no index refresh)
    return subprocess.run(["git", "--no-optional-locks", "-C", str(path), *args],
                          capture_output=True,
                          text=True, check=True).stdout.strip()


def missing_simavr_reason() -> Optional[str]:
    """Why the fil tier cannot run here, in one line, or None."""
    path = simavr_path()
    how = (f"Get it with 'git clone {SIMAVR_URL} ~/simavr' (v1.8 or later) or "
           f"set SIMAVR_PATH; the build needs Debian's libelf-dev.")
    if not (path / "simavr" / "sim" / "sim_avr.c").is_file():
        return f"no simavr source at {path}: the fil tier is SKIPPED. {how}"
    try:
        described = _git(path, "describe", "--tags", "--always")
    except (subprocess.CalledProcessError, OSError) as e:
        return (f"simavr at {path} is not a git checkout ({e}): the fil tier "
                f"is SKIPPED. {how}")
    match = re.match(r"v(\d+)\.(\d+)", described)
    if match and tuple(map(int, match.groups())) < MIN_VERSION:
        return (f"simavr at {path} is {described}, older than v1.8 (its "
                f"interrupts, SPI and Timer1 do not run Klipper): the fil tier "
                f"is SKIPPED. {how}")
    if not Path("/usr/include/libelf.h").exists() and not Path(
            "/usr/include/gelf.h").exists():
        return "libelf-dev is not installed: the fil tier is SKIPPED. " + how
    return None


# One fix flowloop makes to its build copy of simavr (never to SIMAVR_PATH,
# never committed as simavr's code): a timer overflow that simavr handles a
# few cycles late (the overflow falls inside a multi-cycle instruction)
# skipped every compare match due in those cycles for a whole period.
# Klipper's AVR timer sets OCR1A to 0x0000 for the wrap timer that counts
# Timer1 overflows into timer_high; once every few seconds the match was
# skipped, two overflows set one flag, and the firmware's clock fell 65536
# ticks (4.1 ms) behind for good, which skews klippy's clock estimate
# ("Timer too close"). The patch makes such a match fire at once, in the
# overflow's own handler, as the hardware's fired during the instruction.
# (The first version of this patch queued the match for the next cycle; an
# OCR1x, TCNT1 or TCCR1x write in the next instruction re-arms Timer1's
# cycle timers from scratch, and that re-arm keeps only the matches still
# to come in the period, so the queued match was dropped for a whole
# period again: tests/fil/test_fil_timer1.py. Klipper's firmware never
# writes there, so this was not issue 38's missed overflow: that one is
# Klipper's own, after a shutdown; see fil_harness.c's clock guard.)
TIMER_PATCH_FROM = (
    "\t\t\t} else if (p->tov_cycles == p->comp[compi].comp_cycles && !start)\n"
    "\t\t\t\tdispatch[compi](avr, when, param);")
TIMER_PATCH_TO = (
    "\t\t\t} else if (!start && p->comp[compi].comp_cycles < p->tov_cycles) {\n"
    "\t\t\t\t// flowloop: the overflow was handled after this match was\n"
    "\t\t\t\t// due: it matches now, not from a cycle timer that a write\n"
    "\t\t\t\t// re-arming the timer in the next instruction would drop\n"
    "\t\t\t\tavr_timer_comp_on_tov(p, when, compi);\n"
    "\t\t\t\tdispatch[compi](avr, when + p->comp[compi].comp_cycles, p);\n"
    + TIMER_PATCH_FROM)
PATCH_KEY = hashlib.sha256(TIMER_PATCH_TO.encode()).hexdigest()[:6]


def patch_simavr_copy(tree: Path) -> None:
    """Apply flowloop's timer fix to a copy of simavr's source."""
    path = tree / "simavr" / "sim" / "avr_timer.c"
    text = path.read_text()
    if TIMER_PATCH_FROM not in text:
        raise HarnessError(
            f"simavr's {path.name} no longer has the overflow handling"
            f" flowloop fixes (devtools/simavr TIMER_PATCH_FROM): check"
            f" whether this simavr still skips a compare match after a late"
            f" overflow, then update or drop the patch")
    path.write_text(text.replace(TIMER_PATCH_FROM, TIMER_PATCH_TO, 1))


def _simavr_build() -> Tuple[Path, Path]:
    """simavr's patched copy in the cache, built once per commit and patch
    text: (its simavr folder, its libsimavr.a)."""
    source = simavr_path()
    commit = _git(source, "rev-parse", "HEAD")[:12]
    dirty = _git(source, "status", "--porcelain", "--untracked-files=no")
    key = commit + ("-" + hashlib.sha256(dirty.encode()).hexdigest()[:8]
                    if dirty else "") + "-p" + PATCH_KEY
    root = stack.cache_dir() / f"simavr-{key}"
    lib_dir = root / "simavr"
    with stack._locked("simavr"):
        if not (root / ".flowloop-ready").exists():
            stack.log(f"building simavr {key} from {source} into {root}")
            tmp = root.with_name(root.name + ".tmp")
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(source, tmp, symlinks=True,
                            ignore=shutil.ignore_patterns(".git", "obj-*"))
            patch_simavr_copy(tmp)
            # config first: a parallel build races its generated headers
            stack._run(["make", "-C", "simavr", "config", "RELEASE=1"], cwd=tmp)
            stack._run(["make", "-C", "simavr", "libsimavr", "RELEASE=1",
                        f"-j{os.cpu_count() or 2}"], cwd=tmp,
                       log_file=tmp / "build.log")
            stack._prune(stack.cache_dir().glob("simavr-*"), keep=tmp)
            tmp.rename(root)
            (root / ".flowloop-ready").write_text(key)
    libs = list(lib_dir.glob("obj-*/libsimavr.a"))
    if not libs:
        raise RuntimeError(f"simavr built no libsimavr.a under {lib_dir}")
    return lib_dir, libs[0]


def _build_against_simavr(source: Path) -> Path:
    """A host program linked against the patched libsimavr, built into the
    cache once per source text."""
    lib_dir, lib = _simavr_build()
    text = source.read_bytes()
    binary = lib_dir.parent / (
        f"{source.stem}-{hashlib.sha256(text).hexdigest()[:12]}")
    with stack._locked("simavr"):
        if not binary.exists():
            stack.log(f"building {binary.name} against {lib}")
            tmp = binary.with_name(binary.name + ".tmp")
            stack._run(["gcc", "-O2", "-Wall", "-Wextra", "-Werror",
                        "-Wno-unused-parameter", "-o", str(tmp),
                        str(source), "-I", str(lib_dir / "sim"),
                        "-I", str(lib_dir), str(lib), "-lelf", "-lm"])
            tmp.rename(binary)
    return binary


def build_harness() -> Path:
    """The fil_harness binary, built into the cache (simavr once per commit,
    with flowloop's timer fix, the harness once per source text)."""
    return _build_against_simavr(HARNESS_SOURCE)


def run_program(elf: Path, *ranges: Tuple[int, int]) -> List[bytes]:
    """Run a small AVR test program on the patched simavr until it sleeps
    with interrupts off; the bytes of each (data address, length) then."""
    runner = _build_against_simavr(RUNNER_SOURCE)
    args = [f"{address:x}:{length}" for address, length in ranges]
    out = subprocess.run([str(runner), str(elf), *args], capture_output=True,
                         text=True, timeout=60)
    if out.returncode:
        raise HarnessError(f"{elf.name} on simavr: {out.stderr.strip()}")
    return [bytes.fromhex(line[len("data "):])
            for line in out.stdout.splitlines() if line.startswith("data ")]


def firmware_has_ems22(build: stack.KlipperBuild) -> Optional[str]:
    """None when the atmega2560 firmware carries the EMS22 commands, else why not."""
    config = build.dict_dir / "atmega2560.config"
    elf = build.elf("atmega2560")
    if not elf.exists():
        return f"no atmega2560 firmware at {elf}"
    if "WANT_SENSOR_EMS22=y" not in config.read_text():
        return (f"{elf} was built without flowloop's EMS22 option "
                f"(WANT_SENSOR_EMS22 unset in {config}): run 'flowloop install'"
                f" and rebuild")
    return None


class HarnessError(RuntimeError):
    pass


def idle_loop(elf: Path) -> Tuple[int, int]:
    """[start, end) byte addresses of Klipper's AVR idle loop (irq_wait in
    run_tasks: sei; nop; cli; check tasks_status; branch back)."""
    lines = stack._run(["avr-objdump", "-d", "--no-show-raw-insn", str(elf)])
    code = []
    for line in lines.splitlines():
        match = re.match(r"\s+([0-9a-f]+):\s+(\w+)\s*(.*)", line)
        if match:
            code.append((int(match.group(1), 16), match.group(2),
                         match.group(3)))
    for i in range(len(code) - 2):
        if [c[1] for c in code[i:i + 3]] == ["sei", "nop", "cli"]:
            start = code[i][0]
            for address, op, args in code[i + 3:i + 10]:
                if op == "rjmp" and f"0x{start:x}" in args:
                    return start, address + 2
    raise HarnessError(f"no idle loop (sei; nop; cli ... rjmp back) in {elf}")


class Simulator(stack.Process):
    """fil_harness running klipper.elf; klippy opens `pty` as its serial port."""

    def __init__(self, elf: Path, workdir: Path, *, sensor: Dict[str, str],
                 mm_per_step: float, counts_per_mm: float,
                 step_pin: str = "PA4", dir_pin: str = "PA6",
                 heater_pin: Optional[str] = None,
                 adc_channel: Optional[int] = None, adc_mv: int = 0,
                 extra: List[str] = ()):
        """sensor: {'cs': 'PG0'} for hardware SPI, plus {'sclk': .., 'miso': ..}
        for software SPI."""
        self.workdir = workdir
        self.pty = workdir / "mcu-serial"
        self.control_path = workdir / "fil.sock"
        self._sock: Optional[socket.socket] = None
        self._buffer = b""
        self._lock = threading.Lock()  # the hotend thread shares the socket
        cmd = [str(build_harness()), "--elf", str(elf), "--pty", str(self.pty),
               "--control", str(self.control_path), "--cs", sensor["cs"],
               "--step", step_pin, "--dir", dir_pin,
               "--mm-per-step", repr(mm_per_step),
               "--counts-per-mm", repr(counts_per_mm)]
        try:
            start, end = idle_loop(elf)
            cmd += ["--idle-pc", f"{start:x},{end:x}",
                    "--clock-high", f"{data_address(elf, 'timer_high'):x}"]
            cmd += ["--shutdown-flag", f"{shutdown_flag_address(elf):x}"]
        except (HarnessError, RuntimeError):
            pass  # not a Klipper AVR build: no profile (status idle_cycles=0)
        if "sclk" in sensor:
            cmd += ["--sw-spi", f"{sensor['sclk']},{sensor['miso']}"]
        if heater_pin:
            cmd += ["--heater", heater_pin]
        if adc_channel is not None:
            cmd += ["--adc-channel", str(adc_channel), "--adc-mv", str(adc_mv)]
        cmd += list(extra)
        super().__init__("fil_harness", cmd, workdir / "fil_harness.log")

    def wait_ready(self, timeout: float = 10.0) -> None:
        ok = stack.wait_until(lambda: not self.alive() or (
            self.pty.exists() and self.control_path.exists()), timeout, 0.02)
        if not ok or not self.alive():
            output = self.log_tail(1500).strip().splitlines()
            raise HarnessError("the simulator did not start: "
                               + (output[-1] if output else "no output"))

    def control(self, line: str, timeout: float = 5.0) -> str:
        """Send one command, return its one-line answer."""
        with self._lock:
            return self._control(line, timeout)

    def _control(self, line: str, timeout: float) -> str:
        if self._sock is None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self._sock.settimeout(timeout)
            self._sock.connect(str(self.control_path))
        self._sock.sendall(line.encode() + b"\n")
        deadline = time.monotonic() + timeout
        while b"\n" not in self._buffer:
            if time.monotonic() > deadline or not self.alive():
                raise HarnessError(f"no answer to {line!r} from the simulator")
            chunk = self._sock.recv(4096)
            if not chunk:
                raise HarnessError(f"the simulator closed its control socket"
                                   f" on {line!r}")
            self._buffer += chunk
        answer, self._buffer = self._buffer.split(b"\n", 1)
        text = answer.decode()
        if text.startswith("error"):
            raise HarnessError(f"{line!r}: {text}")
        return text

    def status(self) -> Dict[str, str]:
        return dict(part.split("=", 1) for part in self.control("status").split())

    def stop(self, timeout: float = 10.0) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        super().stop(timeout)


class NormalKlippy(stack.Process):
    """klippy in normal mode: its MCU is the simulator behind [mcu] serial."""

    def __init__(self, build: stack.KlipperBuild, venv: stack.Venv, config: Path,
                 workdir: Path):
        self.api_socket = workdir / "klippy.sock"
        cmd = [str(venv.python), str(build.klippy), str(config),
               "-a", str(self.api_socket), "-l", str(workdir / "klippy.log")]
        super().__init__("klippy", cmd, workdir / "klippy.log", cwd=str(build.tree))


class FilPrinter:
    """The simulator and a klippy connected to it, with an API client."""

    def __init__(self, sim: Simulator, klippy: NormalKlippy, api):
        self.sim, self.klippy, self.api = sim, klippy, api
        api.call("gcode/subscribe_output", response_template={})

    def gcode(self, script: str):
        return self.api.gcode(script)

    def console(self) -> List[str]:
        """Console lines (respond_info, errors) since the last call."""
        lines = [msg["params"]["response"] for msg in self.api.remote
                 if "response" in msg.get("params", {})]
        self.api.remote.clear()
        return lines

    def console_until(self, match, timeout: float = 2.0) -> List[str]:
        """Console lines since the last call, read until one of them
        satisfies match(line) or timeout passes. klippy sends a line a
        module registers as a reactor callback after the status that
        reports its cause can already have been answered."""
        lines: List[str] = []

        def arrived():
            self.api.call("info")   # reads what klippy sent before answering
            lines.extend(self.console())
            return any(match(line) for line in lines)
        stack.wait_until(arrived, timeout, 0.05)
        return lines

    def gcode_console(self, script: str) -> List[str]:
        """Run script; the console lines it gave."""
        self.console()
        self.gcode(script)
        return self.console()

    def query(self, obj: str) -> dict:
        return self.api.query(obj)

    def logs(self) -> str:
        return self.sim.log_tail(2000) + "\n" + self.klippy.log_tail(4000)


def start_printer(build: stack.KlipperBuild, venv: stack.Venv, config_text: str,
                  workdir: Path, ready_timeout: float = 30.0,
                  **sim_options) -> FilPrinter:
    """Start the simulator, then klippy on config_text (its '{serial}' is
    replaced by the pty); returns once klippy reports ready."""
    from devtools.klippy_api import KlippyApi
    reason = firmware_has_ems22(build)
    if reason:
        raise HarnessError(reason)
    # klippy compiles its C helper on first use; doing that while the
    # simulator runs would leave the simulation behind the clock.
    stack.build_chelper(build, venv)
    sim = Simulator(build.elf("atmega2560"), workdir, **sim_options)
    klippy = None
    try:
        sim.wait_ready()
        config = workdir / "printer.cfg"
        config.write_text(config_text.replace("{serial}", str(sim.pty)))
        klippy = NormalKlippy(build, venv, config, workdir)
        if not stack.wait_until(lambda: stack.accepts(klippy.api_socket)
                                or not klippy.alive(), ready_timeout):
            raise HarnessError("klippy did not open its API socket")
        api = KlippyApi(klippy.api_socket, timeout=ready_timeout)
        info = stack.wait_until(lambda: _ready_state(api, sim, klippy),
                                ready_timeout, 0.2)
        if info != "ready":
            raise HarnessError(f"klippy is not ready after {ready_timeout:.0f} s"
                               f" (state {_state(api)!r})")
        return FilPrinter(sim, klippy, api)
    except Exception as e:
        logs = sim.log_tail(1500) + (klippy.log_tail(3000) if klippy else "")
        for proc in (klippy, sim):
            if proc is not None:
                proc.stop()
        if isinstance(e, HarnessError):
            raise HarnessError(f"{e}\n{logs}") from None
        raise


def _state(api) -> str:
    try:
        return api.call("info")["state"]
    except (RuntimeError, OSError) as e:
        return f"no answer: {e}"


def _ready_state(api, sim: Simulator, klippy: NormalKlippy):
    if not sim.alive():
        raise HarnessError("the simulator stopped")
    if not klippy.alive():
        raise HarnessError("klippy stopped")
    state = _state(api)
    if state in ("shutdown", "error"):
        # its message from klippy itself: the log is written by a thread and
        # may not hold it yet
        try:
            message = api.call("info").get("state_message", "")
        except (RuntimeError, OSError) as e:
            message = f"no answer: {e}"
        raise HarnessError(f"klippy state {state}: {message.strip()}")
    return "ready" if state == "ready" else None


def stop_printer(printer: FilPrinter) -> None:
    try:
        printer.api.close()
    finally:
        printer.klippy.stop()
        printer.sim.stop()


def data_address(elf: Path, symbol: str) -> int:
    """The SRAM address of a firmware variable (for the harness's peek)."""
    out = stack._run(["avr-nm", str(elf)])
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2] == symbol:
            return int(parts[0], 16) - 0x800000
    raise HarnessError(f"no symbol {symbol} in {elf}")


# FirmwareClock reads when the simulation is less than this behind the wall
READ_LAG_MS = 1.0


class FirmwareClock:
    """Klipper's own AVR clock (timer_high: Timer1 overflows it counted)
    against simulated cycles and the wall clock."""

    def __init__(self, printer: FilPrinter, elf: Path):
        self.sim = printer.sim
        self.address = data_address(elf, "timer_high")

    def read(self, timeout_s: float = 2.0):
        """(wall monotonic s, firmware clock in ticks (64k resolution), cycles),
        read while the simulation keeps up with the wall clock: read while
        it catches up from a stall (the machine's, not the firmware's), the
        clock would read that stall as a slow firmware. After timeout_s of
        lag, what it reads then."""
        end = time.monotonic() + timeout_s
        while True:
            answer = dict(p.split("=") for p in self.sim.control(
                f"peek {self.address}").split())
            now = time.monotonic()
            if float(answer["lag_ms"]) < READ_LAG_MS or now > end:
                return now, int(answer["value"]) << 16, int(answer["cycle"])
            time.sleep(0.01)


# Klipper's src/sched.c: static struct { struct timer *timer_list,
# *last_insert; int8_t tasks_status, tasks_busy; uint8_t shutdown_status,
# shutdown_reason; } SchedStatus (AVR pointers are 2 bytes). LTO names it
# SchedStatus.lto_priv.N.
SHUTDOWN_STATUS_OFFSET = 6


def shutdown_flag_address(elf: Path) -> int:
    """The SRAM address of Klipper's SchedStatus.shutdown_status (nonzero
    while the firmware is shut down), for the harness's clock guard."""
    out = stack._run(["avr-nm", str(elf)])
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and re.fullmatch(r"SchedStatus(\.lto_priv\.\d+)?",
                                            parts[2]):
            return int(parts[0], 16) - 0x800000 + SHUTDOWN_STATUS_OFFSET
    raise HarnessError(f"no symbol SchedStatus in {elf}")


# The fil printer's thermistor (tests/fil/fil_printer.cfg): a beta curve,
# so the voltage the harness puts on the pin is what klippy converts back.
THERMISTOR_R25_OHM, THERMISTOR_BETA = 100000., 3950.
PULLUP_OHM, ADC_VREF_MV = 4700., 5000.


def thermistor_mv(temp_c: float) -> float:
    """The thermistor pin's voltage (pull-up to 5 V) at temp_c."""
    kelvin = temp_c + 273.15
    r = THERMISTOR_R25_OHM * math.exp(THERMISTOR_BETA * (1 / kelvin - 1 / 298.15))
    return ADC_VREF_MV * r / (r + PULLUP_OHM)


class HotendDriver:
    """flowloop's hotend model between the heater pin and the thermistor pin,
    and its melt line as the filament's grip, stepped every `period_s` in a
    thread: the heater's duty (from the pin) is the model's power, the model's
    temperature goes back to the ADC pin, and the grip the harness applies to
    the shaft is what the melt line lets through at the extruder's demand."""

    def __init__(self, sim: Simulator, model, melt_line, mm_per_step: float,
                 filament_area_mm2: float, period_s: float = 0.1,
                 melt_time_s: float = 0.3):
        self.sim, self.model, self.melt_line = sim, model, melt_line
        self.mm_per_step, self.area = mm_per_step, filament_area_mm2
        self.period_s, self.melt_time_s = period_s, melt_time_s
        self.demand_mm3_s = 0.0
        self.grip = 1.0
        self.duty = 0.0
        self.error: Optional[BaseException] = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._last = self._read()
        self.sim.control("heater")  # start the duty window now
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def __enter__(self) -> HotendDriver:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        """Stopped; an error its thread met fails the block (unless the
        block failed first)."""
        self.stop()
        if exc[0] is None and self.error is not None:
            raise HarnessError(f"the hotend driver failed: {self.error!r}")

    def _read(self):
        status = self.sim.status()
        return float(status["sim_s"]), int(status["steps"])

    def _run(self) -> None:
        from flowloop.sensor.twin import melt_grip
        try:
            while not self._stop.wait(self.period_s):
                sim_s, steps = self._read()
                duty = float(self.sim.control("heater").split()[0].split("=")[1])
                dt = sim_s - self._last[0]
                if dt <= 0:
                    continue
                flow = max(0, steps - self._last[1]) * self.mm_per_step \
                    * self.area / dt
                self._last = (sim_s, steps)
                alpha = 1.0 - math.exp(-dt / self.melt_time_s)
                self.demand_mm3_s += alpha * (flow - self.demand_mm3_s)
                grip = (melt_grip(self.melt_line, self.demand_mm3_s,
                                  self.model.temp_c) if flow > 0 else 1.0)
                if abs(grip - self.grip) > 0.001:
                    self.sim.control(f"grip {grip:.4f}")
                    self.grip = grip
                self.duty = duty
                self.model.fixed_power_w = duty * self.model.params.max_power_w
                self.model.advance(self.model.time_s + dt, flow * grip)
                self.sim.control(f"adc {thermistor_mv(self.model.temp_c):.0f}")
        except BaseException as e:  # reported by the test that reads .error
            self.error = e
