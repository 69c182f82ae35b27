"""tools/vcan-run from the outside: exit status, environment and directory pass through, and
the user-mode-linux guest never outlives the runner (timeout, interrupt, runner killed). Runs
natively; boots UML twice, plus two boots cut short after about a second."""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fixtures.bus import in_ci
from fixtures.uml import BOOT_TIMEOUT, VCAN_RUN, runner_mode, vcan_run


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


def test_what_the_command_left_running_ends_with_it(uml):
    """A background job the command leaves (``bash -c 'rocoma-can sim ... & ...'``) holds
    the pipes its output comes through: the guest stayed up until the timeout (1800 s).
    It is ended as the command ends, and said; the command's status is the runner's."""
    result = vcan_run("bash", "-c", "sleep 600 & sleep 600 & echo started; exit 3",
                      ROCOMA_VCAN_TIMEOUT="120", **uml)

    assert result.returncode == 3, result.stderr
    assert result.stdout == "started\n"
    assert "vcan-run (guest): the command ended; ending what it left running (SIGTERM)" \
        in result.stderr
    assert group_members(guest_pid(result.stderr)) == []


def test_a_leftover_that_ignores_sigterm_is_killed(uml):
    result = vcan_run("bash", "-c", "trap '' TERM; sleep 600 & exit 0",
                      ROCOMA_VCAN_TIMEOUT="120", **uml)
    assert result.returncode == 0, result.stderr
    assert "ending what it left running" in result.stderr


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


# ----------------------------------------------------------------- which guest kernel boots

sys.path.insert(0, str(VCAN_RUN.parent))
import uml_kernels  # noqa: E402  (tools/ is no package)

#: A kernel as Debian bookworm's linux.uml behaves on an Intel host with AVX-512/AMX under
#: host kernel 6.18: it starts, dies at its first user process, says so on its console (the
#: one its command line names) and aborts. Each boot leaves a line in a file of the test's.
PANICKING_KERNEL = """#!/bin/bash
# {mark}
case "$1" in --version) echo 6.1.176; exit 0 ;; esac
echo boot >> {boots}
console=0
for arg; do case $arg in console=tty*) console=${{arg#console=tty}} ;; esac; done
out=1
for arg; do case $arg in "con$console="*fd:*) out=${{arg##*fd:}} ;; esac; done
{{
    echo "Linux version 6.1.176 (a stand-in for Debian's 6.1um4)"
    echo "Run /tmp/vcan-run-x/init as init process"
    echo "userspace - ptrace set fp regs failed, errno = 14"
    echo "Kernel panic - not syncing: Attempted to kill init! exitcode=0x0000000b"
    echo "CPU: 0 PID: 1 Comm: init Not tainted 6.1.176 #1"
    echo "Stack:"
    echo " 606944ba 607e7fcd 66843c60 6067bb96"
    echo "Call Trace:"
    echo " [<6002df68>] ? flush_tlb_page+0x116/0x1dd"
}} >&"$out"
{end}
"""
#: How the kernel ends after its panic: UML aborts (os_dump_core); one that hangs instead
#: must not hold the runner for the proof's whole time budget.
ABORTS, HANGS = "kill -ABRT $$", "exec sleep 600"


@pytest.fixture
def panicking_kernel(tmp_path) -> tuple[Path, Path]:
    """The kernel (new for each test: its own verdict) and the file counting its boots."""
    return make_panicking_kernel(tmp_path, ABORTS)


def make_panicking_kernel(tmp_path: Path, end: str) -> tuple[Path, Path]:
    kernel, boots = tmp_path / "linux.uml", tmp_path / "boots"
    kernel.write_text(PANICKING_KERNEL.format(mark=tmp_path, boots=boots, end=end))
    kernel.chmod(0o755)
    return kernel, boots


@pytest.fixture
def own_verdicts(tmp_path) -> dict[str, str]:
    """A cache whose verdicts are the test's own, whose fetched kernels are the machine's (a
    fetch is some 70 MB: once a machine, not once a test)."""
    shared = uml_kernels.cache_dir() / "kernels"
    shared.mkdir(parents=True, exist_ok=True)
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "kernels").symlink_to(shared)
    return {"ROCOMA_VCAN_CACHE": str(cache)}


@pytest.mark.parametrize("end", [ABORTS, HANGS], ids=["aborts", "hangs-after-its-panic"])
def test_a_kernel_that_dies_booting_is_said_at_once_with_its_last_console_lines(
        uml, tmp_path, end):
    """No kernel boots (the installed one panics, nothing fetched, fetching off): --check
    and a run both fail at once, 125, with the guest's own last words (its stack dump left
    out), not a hint about memory; the command never runs; the verdict is kept (a kernel
    that hangs after its panic is killed a few seconds after it, not at the proof's 180 s)."""
    kernel, boots = make_panicking_kernel(tmp_path, end)
    env = dict(uml, ROCOMA_VCAN_CACHE=str(tmp_path / "empty"), ROCOMA_VCAN_UML=str(kernel),
               ROCOMA_VCAN_FETCH="0")
    check = vcan_run("--check", **env)
    ran = tmp_path / "ran"
    run = vcan_run("touch", str(ran), **env)

    for result in (check, run):
        assert result.returncode == 125, result.stderr
        assert "no user-mode-linux kernel boots on this host" in result.stderr
        assert f"{kernel} (kernel 6.1.176): the guest's last console lines:\n" \
               "    Linux version 6.1.176 (a stand-in for Debian's 6.1um4)\n" \
               "    Run /tmp/vcan-run-x/init as init process\n" \
               "    userspace - ptrace set fp regs failed, errno = 14\n" \
               "    Kernel panic - not syncing: Attempted to kill init! exitcode=0x0000000b\n" \
               "  newer kernels are not fetched (ROCOMA_VCAN_FETCH=0)" in result.stderr
        assert "flush_tlb_page" not in result.stderr and "MEM" not in result.stderr
    assert not ran.exists()
    assert boots.read_text() == "boot\n", "the verdict was not kept: the kernel booted again"


def test_a_kernel_that_does_not_boot_gives_way_to_a_newer_debian_one(
        uml, panicking_kernel, own_verdicts, tmp_path):
    """The installed kernel panics: a newer suite's user-mode-linux (fetched into the cache
    through the system's apt sources, once a machine) is proven, chosen and named in one line
    with why; the command runs in it with vcan up and the modules of the kernel that booted;
    the installed kernel is not booted again."""
    kernel, boots = panicking_kernel
    env = dict(uml, **own_verdicts, ROCOMA_VCAN_UML=str(kernel))
    probe = ("import os, socket; socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)"
             ".close(); print(os.uname().release, os.environ['ROCOMA_VCAN_RUNNER'],"
             " [int(open(f'/sys/class/net/{n}/flags').read(), 16) & 1 for n in"
             " ('vcan0', 'vcan1')])")
    result = vcan_run(sys.executable, "-c", probe, cwd=tmp_path, **env)
    again = vcan_run("--check", **env)

    assert result.returncode == 0, result.stderr
    release, runner, up = result.stdout.split(maxsplit=2)
    assert (runner, up) == ("uml", "[1, 1]\n")
    chosen = [line for line in result.stderr.splitlines() if "guest kernel:" in line]
    assert len(chosen) == 1, result.stderr
    assert re.fullmatch(
        rf"vcan-run: guest kernel: Debian \S+'s user-mode-linux (\S+) \((\S+)\) \(kernel "
        rf"{re.escape(release)}\): {re.escape(str(kernel))} \(kernel 6\.1\.176\) does not boot "
        r"on this host \(userspace - ptrace set fp regs failed, errno = 14 \| Kernel panic - "
        r"not syncing: Attempted to kill init! exitcode=0x0000000b\)", chosen[0]), chosen[0]
    directory = Path(re.search(r"user-mode-linux \S+ \((\S+)\)", chosen[0]).group(1))
    assert directory.parent.resolve() == (uml_kernels.cache_dir() / "kernels").resolve()
    assert (directory / "modules" / release / "kernel" / "drivers/net/can/vcan.ko").is_file()
    assert again.returncode == 0 and chosen[0] in again.stderr, again.stderr
    assert boots.read_text() == "boot\n"


def test_a_fetched_kernel_starts_through_the_loader_beside_it(tmp_path):
    """How a fetched kernel runs on the C library of its own suite, system files untouched:
    its program interpreter is rewritten to a path relative to its directory, from which it
    is started. Shown on a copy of /bin/true and this host's own loader."""
    binary = tmp_path / "true"
    shutil.copy("/bin/true", binary)
    original = Path("/bin/true").read_bytes()
    loader = next(Path(p) for p in ("/lib64/ld-linux-x86-64.so.2", "/lib/ld-linux-aarch64.so.1")
                  if Path(p).exists())
    (tmp_path / "lib").mkdir()
    shutil.copy(loader, tmp_path / "lib" / loader.name)

    written = uml_kernels.patch_loader(binary, tmp_path / "lib")

    assert written == f"lib/{loader.name}"
    assert subprocess.run([str(binary)], cwd=tmp_path).returncode == 0
    with pytest.raises(FileNotFoundError):  # elsewhere the relative loader is not found
        subprocess.run([str(binary)], cwd="/")
    assert Path("/bin/true").read_bytes() == original


@pytest.mark.parametrize(("member", "kept_as"), [
    ("./usr/bin/linux.uml", "linux.uml"),
    ("./usr/lib/uml/modules/7.2.7/kernel/net/can/can-raw.ko",
     "modules/7.2.7/kernel/net/can/can-raw.ko"),
    ("./usr/lib/uml/modules/7.2.7/kernel/drivers/net/can/dev/can-dev.ko",
     "modules/7.2.7/kernel/drivers/net/can/dev/can-dev.ko"),
    ("./usr/lib/uml/modules/7.2.7/kernel/fs/btrfs/btrfs.ko", None),
    ("./usr/lib/x86_64-linux-gnu/libc.so.6", "lib/libc.so.6"),
    ("./lib/x86_64-linux-gnu/ld-linux-x86-64.so.2", "lib/ld-linux-x86-64.so.2"),
    ("./usr/lib/x86_64-linux-gnu/gconv/UTF-16.so", None),
    ("./usr/share/doc/libc6/copyright", None),
])
def test_a_fetched_kernel_keeps_only_what_the_guest_needs(member, kept_as):
    assert uml_kernels.wanted(member) == kept_as
