"""rocoma_can/cli/doctor.py, drivers/link/can_link.py: ``rocoma-can doctor`` against live links:
vcan0 as configured, a link that is missing, vcan0 set down, and a real CAN controller (slcan on a
pseudo-terminal, kind "can": a bit rate, a state, restart-ms) at another bit rate and bus-off."""
from __future__ import annotations

import fcntl
import json
import os
import struct
import subprocess
import sys
import termios
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from fixtures.budgets import GUEST_STALL, within

EXAMPLE = Path(__file__).resolve().parents[2] / "rocoma_can" / "examples" / "bench_vcan.yaml"
CLI_BUDGET = within(10, GUEST_STALL)
N_SLCAN = 17  # the slcan line discipline (linux/tty.h)
# tools/vcan-run's guest names the module directory of the kernel that booted (Debian's, or
# one it fetched into its cache)
SLCAN_MODULE = Path(os.environ.get("ROCOMA_VCAN_MODULES",
                                   f"/usr/lib/uml/modules/{os.uname().release}/kernel"),
                    "drivers/net/can/slcan/slcan.ko")


def doctor(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rocoma_can", "doctor", *args],
                          capture_output=True, text=True, timeout=CLI_BUDGET)


def config(tmp_path: Path, channel: str, bitrate: int = 1_000_000) -> str:
    data = yaml.safe_load(EXAMPLE.read_text())
    data["bus"] = {"interface": "socketcan", "channel": channel, "bitrate": bitrate}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def checks_of(done: subprocess.CompletedProcess[str]) -> dict[str, dict[str, str]]:
    return {c["name"]: c for c in json.loads(done.stdout)}


def test_vcan0_as_configured_passes_with_no_bit_rate_to_judge(tmp_path):
    done = doctor(str(EXAMPLE))
    print(done.stdout)  # the README's example output
    assert done.returncode == 0, done.stdout + done.stderr
    checks = checks_of(doctor(str(EXAMPLE), "--json"))
    assert checks["vcan0: exists"]["status"] == "ok"
    assert checks["vcan0: up"]["status"] == "ok"
    assert checks["vcan0: bit rate"]["status"] == "n/a"
    assert "vcan has no bit rate" in checks["vcan0: bit rate"]["found"]


def test_a_missing_interface_fails_naming_it_and_how_to_create_it(tmp_path):
    done = doctor(config(tmp_path, "vcan7"))
    assert done.returncode == 1
    assert "FAIL  vcan7: exists" in done.stdout and "no network interface 'vcan7'" in done.stdout
    assert "fix: sudo modprobe vcan && sudo ip link add dev vcan7 type vcan" in done.stdout


def test_vcan0_down_fails_with_the_command_that_brings_it_up(tmp_path, vcan_link):
    vcan_link("vcan0", "down")
    done = doctor(str(EXAMPLE), "--json")
    assert done.returncode == 1
    up = checks_of(done)["vcan0: up"]
    assert up["status"] == "fail" and up["fix"] == "sudo ip link set vcan0 up"


@pytest.fixture
def slcan() -> Iterator[tuple[str, int]]:
    """(name, pty master) of an slcan controller, up at 1 Mbit/s: a CAN device with bit
    timing and a state, which vcan is not. The master side is the "adapter": what is written
    there (b"sb256256\\r": bus-off) the driver takes as the adapter's report."""
    if not SLCAN_MODULE.exists():
        pytest.skip(f"no slcan module at {SLCAN_MODULE} (the user-mode-linux guest has it)")
    subprocess.run(["insmod", str(SLCAN_MODULE)], capture_output=True, timeout=30)
    before = set(os.listdir("/sys/class/net"))
    master, slave = os.openpty()
    try:
        fcntl.ioctl(slave, termios.TIOCSETD, struct.pack("i", N_SLCAN))
    except OSError as exc:
        pytest.skip(f"cannot attach slcan to a pty: {exc}")
    (name,) = set(os.listdir("/sys/class/net")) - before
    stop = threading.Event()

    def adapter() -> None:  # reads what the driver sends (open, bit rate), so it never blocks
        while not stop.is_set():
            try:
                os.read(master, 256)
            except OSError:
                return

    threading.Thread(target=adapter, daemon=True).start()
    for step in (["type", "can", "bitrate", "1000000"], ["txqueuelen", "128"], ["up"]):
        done = subprocess.run(["ip", "link", "set", name, *step], capture_output=True,
                              text=True, timeout=30)
        assert done.returncode == 0, done.stderr
    yield name, master
    stop.set()
    subprocess.run(["ip", "link", "set", name, "down"], capture_output=True, timeout=30)
    os.close(slave)
    os.close(master)


def test_a_controller_at_another_bit_rate_fails_and_bus_off_fails(tmp_path, slcan):
    name, adapter = slcan
    at_rate = checks_of(doctor(config(tmp_path, name, 1_000_000), "--json"))
    assert at_rate[f"{name}: bit rate"]["status"] == "ok"
    assert at_rate[f"{name}: controller state"]["found"] == "ERROR-ACTIVE"
    assert at_rate[f"{name}: restart-ms"]["status"] == "warn"

    done = doctor(config(tmp_path, name, 500_000), "--json")
    assert done.returncode == 1
    rate = checks_of(done)[f"{name}: bit rate"]
    assert rate["status"] == "fail" and "bitrate 500000" in rate["fix"]

    os.write(adapter, b"sb256256\r")  # the adapter reports bus-off
    deadline = time.monotonic() + within(0.1, GUEST_STALL)
    carrier = Path(f"/sys/class/net/{name}/carrier")  # bus-off takes the carrier away
    while carrier.read_text().strip() != "0" and time.monotonic() < deadline:
        time.sleep(0.05)
    done = doctor(config(tmp_path, name, 1_000_000), "--json")
    assert done.returncode == 1
    state = checks_of(done)[f"{name}: controller state"]
    assert state["status"] == "fail" and state["found"].startswith("BUS-OFF")
