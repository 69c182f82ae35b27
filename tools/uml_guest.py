"""The processes of a user-mode-linux guest, as tools/vcan-run runs them: the guest's console
kept for its last words, its output forwarded as it comes, a watchdog that kills the guest
when the runner dies without cleaning up, and the reaping of everything the guest started.

Apart from vcan-run so that the runner reads as its decisions (which way, which kernel, what
to say) and this as the mechanics they rest on."""
from __future__ import annotations

import collections
import ctypes
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path


class Interrupted(Exception):
    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


class Console:
    """The last lines a guest wrote to a stream kept here (its kernel's console, or all of a
    proof boot's output): what to show when the guest dies."""

    KEEP = 80

    def __init__(self) -> None:
        self.lines: collections.deque[str] = collections.deque(maxlen=self.KEEP)
        self._partial = b""
        self._lock = threading.Lock()
        self.panicked_at: float | None = None  # (monotonic) when the kernel said it panicked

    def write(self, chunk: bytes) -> None:
        with self._lock:
            *whole, self._partial = (self._partial + chunk).split(b"\n")
            self.lines.extend(line.decode(errors="replace").rstrip() for line in whole)
            if self.panicked_at is None and any(b"Kernel panic" in line for line in whole):
                self.panicked_at = time.monotonic()

    def tail(self) -> list[str]:
        with self._lock:
            rest = [self._partial.decode(errors="replace").rstrip()] if self._partial else []
            return [line for line in [*self.lines, *rest] if line]


def to_fd(fd: int):
    def write(chunk: bytes) -> None:
        try:
            os.write(fd, chunk)
        except OSError:  # our reader went away; keep draining so the guest never blocks
            pass
    return write


def forward(src, write) -> None:
    """Copy a guest's stream as it comes (pytest output stays live)."""
    while chunk := os.read(src.fileno(), 65536):
        write(chunk)
    src.close()


# A kernel's dying words without its stack dump: what a reader needs is the line before the
# panic and the panic itself.
NOISE = re.compile(r"^\s*(\[<[0-9a-f]+>\]|Stack:|Call Trace:|CPU: |Modules linked in:|"
                   r"---\[ end|[0-9a-f]{8,16}( [0-9a-f]{8,16})*$)")


def last_words(lines: list[str], count: int = 6) -> list[str]:
    """The guest's last ``count`` console lines that say something, up to its first panic."""
    said = []
    for line in lines:
        line = re.sub(r"^<\d>", "", line).rstrip()
        if not line or NOISE.match(line):
            continue
        said.append(line)
        if "Kernel panic" in line:
            break
    return said[-count:]


def become_subreaper() -> None:
    """Orphaned UML helpers then become our children, so we can reap every one of them."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
    except (OSError, AttributeError):
        pass


# Kills the guest's process group and removes its state directory when its stdin closes, i.e.
# when the runner is gone without having cleaned up (SIGKILL): UML helpers would otherwise run
# on forever.
WATCHDOG = """
import os, shutil, signal, sys
sys.stdin.buffer.read()
try:
    os.killpg(int(sys.argv[1]), signal.SIGKILL)
except ProcessLookupError:
    pass
shutil.rmtree(sys.argv[2], ignore_errors=True)
"""


def start_watchdog(pgid: int, state: Path) -> tuple[subprocess.Popen, int]:
    """The watchdog and the pipe end to keep open while the guest lives."""
    read_end, write_end = os.pipe()
    watchdog = subprocess.Popen([sys.executable, "-c", WATCHDOG, str(pgid), str(state)],
                                stdin=read_end,
                                stdout=subprocess.DEVNULL, start_new_session=True)
    os.close(read_end)
    return watchdog, write_end


def kill_and_reap(pgid: int, leader: subprocess.Popen, watchdog: subprocess.Popen,
                  say: Callable[[str], None]) -> None:
    """Kill the guest's whole process group and wait (bounded) until none of it is left."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    watchdog.kill()  # before the group id can be freed and reused: it must not signal that
    watchdog.wait()
    leader.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            pid, _ = os.waitpid(-pgid, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            time.sleep(0.02)
    say(f"warning: processes of group {pgid} are still exiting")


def exited(pid: int) -> bool:
    """Without reaping: the group id stays reserved until we have killed the whole group."""
    info = os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT)
    return info is not None
