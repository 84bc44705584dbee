"""The c tier: mcu_sensor's frame header on the host compiler, and the
sensor built inside the patched Klipper tree."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from flowloop.sensor import ems22

PROJECT = Path(__file__).resolve().parents[2]
VECTORS = PROJECT / "tests" / "data" / "ems22_vectors.json"
STATUS_CODES = {name: code for code, name in enumerate(ems22.STATUS_NAMES)}


@pytest.fixture(scope="module")
def frame_test(compile_c):
    return compile_c("ems22_frame_test.c")


def _vector_lines(vectors) -> str:
    return "".join(f"{v['raw']} {v['offset']} {STATUS_CODES[v['status']]} "
                   f"{v['position']}\n" for v in vectors)


def test_header_decodes_shared_vectors_and_the_bit_model(frame_test):
    vectors = json.loads(VECTORS.read_text())
    proc = subprocess.run([str(frame_test)], input=_vector_lines(vectors),
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout
    assert f"vectors: {len(vectors)} checked" in proc.stdout
    assert "model: 262144 reads checked" in proc.stdout
    # 1024 positions x 3 flag sets (none, MagINC, MagDEC) with OCF
    assert "good: 3072 of 65536 frames" in proc.stdout


def test_the_c_test_notices_a_wrong_vector(frame_test):
    v = dict(json.loads(VECTORS.read_text())[0])
    assert v["status"] == "ok"
    v["position"] = (v["position"] + 1) % 1024
    proc = subprocess.run([str(frame_test)], input=_vector_lines([v] * 20),
                          capture_output=True, text=True)
    assert proc.returncode != 0 and "expected" in proc.stdout


def test_header_and_python_agree_on_the_record_layout():
    header = (PROJECT / "mcu_sensor" / "ems22_frame.h").read_text()
    for name, value in (("READ_BYTES", ems22.READ_BYTES),
                        ("HEADER_BYTES", ems22.HEADER_BYTES),
                        ("PLAIN_BYTES", ems22.PLAIN_BYTES),
                        ("ERROR_RECORD_BYTES", ems22.ERROR_RECORD_BYTES),
                        ("KIND_READ", ems22.KIND_READ),
                        ("KIND_ERROR", ems22.KIND_ERROR),
                        ("MAX_MSG_BYTES", ems22.MAX_MSG_BYTES),
                        ("TCODE_ERROR", f"0x{ems22.TCODE_ERROR:x}"),
                        ("PLAIN_TCODES", ems22.PLAIN_TCODES),
                        ("POSITION_SHIFT", ems22.POSITION_SHIFT)):
        assert f"#define EMS22_{name} {value}\n" in header
    assert ("#define EMS22_READ_RECORD_BYTES (2 + 1 + EMS22_READ_BYTES)\n"
            in header and ems22.READ_RECORD_BYTES == 2 + 1 + ems22.READ_BYTES)
    assert ("#define EMS22_MAX_BATCH_BYTES (EMS22_MAX_MSG_BYTES"
            " - EMS22_READ_RECORD_BYTES + 1)\n" in header
            and ems22.MAX_BATCH_BYTES
            == ems22.MAX_MSG_BYTES - ems22.READ_RECORD_BYTES + 1)
    # kinds are below OCF: no good frame starts like a whole-read or error record
    assert max(ems22.KIND_READ, ems22.KIND_ERROR) < ems22.OCF


def test_a_message_is_as_long_as_klippers_sensor_bulk_buffer(klipper_build):
    header = (klipper_build.tree / "src" / "sensor_bulk.h").read_text()
    assert f"uint8_t data[{ems22.MAX_MSG_BYTES}];" in header


@pytest.mark.parametrize("target", ["linuxprocess", "atmega2560"])
def test_patched_klipper_has_the_sensor_commands(klipper_build, target):
    data = json.loads(klipper_build.dictionary(target).read_text())
    assert ems22.CONFIG_CMD in data["commands"]
    assert ems22.QUERY_CMD in data["commands"]
    assert ems22.BULK_DATA_MSG in data["responses"]


@pytest.mark.parametrize("target", ["linuxprocess", "atmega2560"])
def test_sensor_built_without_warnings(klipper_build, target):
    log_path = klipper_build.dict_dir / f"{target}.log"
    if not log_path.exists():
        pytest.skip("this build cache keeps no build log (devtools/stack.py)")
    log = log_path.read_text()
    assert "sensor_ems22" in log  # it was compiled in this build
    assert "warning:" not in log, log


def test_atmega2560_build_has_no_software_division(klipper_build):
    tool = klipper_build.tree / "scripts" / "check-software-div.sh"
    if shutil.which("objdump") is None:
        pytest.skip("no objdump")
    proc = subprocess.run([str(tool), str(klipper_build.dict_dir / "atmega2560.config"),
                           str(klipper_build.elf("atmega2560"))],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout


def test_atmega2560_elf_links_the_sensor(klipper_build):
    nm = shutil.which("avr-nm")
    if nm is None:
        pytest.skip("no avr-nm")
    out = subprocess.run([nm, str(klipper_build.elf("atmega2560"))],
                         capture_output=True, text=True).stdout
    # LTO renames and inlines: look for the command handler and the timer
    assert "command_query_ems22" in out and "ems22_event" in out
