"""tools/vcan-run from the outside: exit status, environment and directory pass through, and
the user-mode-linux guest never outlives the runner (timeout, interrupt, runner killed). Runs
natively; boots UML twice, plus two boots cut short after about a second."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fixtures.bus import in_ci

VCAN_RUN = Path(__file__).resolve().parents[1] / "tools" / "vcan-run"
BOOT_TIMEOUT = 300  # generous: a shared 2-core machine


def vcan_run(*command: str, cwd: Path | None = None, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(VCAN_RUN), *command], cwd=cwd,
                          env=dict(os.environ, **env), capture_output=True, text=True,
                          timeout=BOOT_TIMEOUT)


def runner_mode(**env: str) -> str | None:
    result = vcan_run("--check", **env)
    return result.stdout.strip() if result.returncode == 0 else None


@pytest.fixture(scope="module")
def uml() -> dict[str, str]:
    """Environment that makes the runner use user-mode-linux; skipped where it is not
    installed, unless under CI on a kernel without vcan (tools/test installs it there)."""
    if runner_mode(ROCOMA_VCAN_MODE="uml") != "uml":
        message = "user-mode-linux is not installed: the UML runner tests cannot run"
        if in_ci() and runner_mode() != "native":
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    return {"ROCOMA_VCAN_MODE": "uml"}


def group_members(pgid: int) -> list[int]:
    """Live processes (not zombies) in process group `pgid`."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            members.append(int(stat.parent.name))
    return members


def guest_pid(stderr: str) -> int:
    match = re.search(r"linux\.uml pid (\d+)", stderr)
    assert match, f"runner did not name the guest process: {stderr!r}"
    return int(match.group(1))


PROBE = """
import os, socket, sys
socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
up = [int(open(f"/sys/class/net/{n}/flags").read(), 16) & 1 for n in ("vcan0", "vcan1")]
print(os.environ["PROBE_MARK"], os.getcwd(), os.environ["ROCOMA_VCAN_RUNNER"], up)
print("to stderr", file=sys.stderr)
sys.exit(7)
"""


def test_status_environment_and_directory_pass_through(tmp_path):
    mode = runner_mode()
    if mode is None:
        message = "tools/vcan-run --check: neither native vcan nor user-mode-linux here"
        if in_ci():
            pytest.fail(message, pytrace=False)
        pytest.skip(message)

    result = vcan_run(sys.executable, "-c", PROBE, cwd=tmp_path, PROBE_MARK="mark-42")

    assert result.returncode == 7, result.stderr
    assert result.stdout == f"mark-42 {tmp_path} {mode} [1, 1]\n"
    assert "to stderr" in result.stderr
    assert ("natively" if mode == "native" else "inside user-mode-linux") in result.stderr


def test_a_missing_way_fails_with_the_install_command():
    result = vcan_run("true", ROCOMA_VCAN_MODE="uml", ROCOMA_VCAN_UML="/nonexistent/linux.uml")
    assert result.returncode == 125
    assert "sudo apt-get install -y user-mode-linux" in result.stderr

    result = vcan_run("true", ROCOMA_VCAN_MODE="sideways")
    assert result.returncode == 125
    assert "expected auto, native or uml" in result.stderr


def test_timeout_kills_the_whole_guest(uml):
    result = vcan_run("sleep", "600", ROCOMA_VCAN_TIMEOUT="1", **uml)

    assert result.returncode == 124
    assert "timed out after 1 s" in result.stderr
    assert group_members(guest_pid(result.stderr)) == []


def test_interrupt_kills_the_whole_guest_and_reports_the_signal(uml, tmp_path):
    started = tmp_path / "started"
    out, err = (tmp_path / "out").open("w+"), (tmp_path / "err").open("w+")
    runner = subprocess.Popen(
        [sys.executable, str(VCAN_RUN), "sh", "-c", f"touch {started}; exec sleep 600"],
        env=dict(os.environ, **uml), stdout=out, stderr=err)
    try:
        deadline = time.monotonic() + BOOT_TIMEOUT
        while not started.exists() and runner.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert started.exists(), "the command never started inside the guest"
        runner.send_signal(signal.SIGINT)
        status = runner.wait(timeout=60)
    finally:
        if runner.poll() is None:
            runner.kill()
            runner.wait(timeout=60)
        out.close()
        err.close()
    stderr = (tmp_path / "err").read_text()

    assert status == 128 + signal.SIGINT, stderr
    assert "interrupted by signal 2" in stderr
    assert group_members(guest_pid(stderr)) == []


def test_a_killed_runner_takes_the_guest_with_it(uml, tmp_path):
    err_path = tmp_path / "err"
    with err_path.open("w") as err:
        runner = subprocess.Popen([sys.executable, str(VCAN_RUN), "sleep", "600"],
                                  env=dict(os.environ, **uml), stdout=subprocess.DEVNULL,
                                  stderr=err)
    try:
        deadline = time.monotonic() + 60
        while "linux.uml pid" not in err_path.read_text() and time.monotonic() < deadline:
            time.sleep(0.02)
        pgid = guest_pid(err_path.read_text())
        kernel_argv = Path(f"/proc/{pgid}/cmdline").read_bytes().decode().split("\0")
        state = Path(next(a for a in kernel_argv if a.startswith("init="))[5:]).parent
        time.sleep(0.5)  # let the guest spawn its helper processes
    finally:
        runner.kill()  # no chance to clean up: the watchdog must
        runner.wait(timeout=60)

    deadline = time.monotonic() + 30
    while (group_members(pgid) or state.exists()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert group_members(pgid) == []
    assert not state.exists(), "the guest's state directory was left behind"
