"""rocoma_can/cli/console.py, rocoma_can/cli/main.py: a reader that goes away (``rocoma-can status |
head -3``): every verb that prints stops quietly, exit 141 (128 + SIGPIPE), no BrokenPipeError
traceback; ``run`` goes on and says once that its lines go to stderr (cli/console.py). Each command
runs in a process of its own (fixtures/cli_child.py) with stdout a pipe whose reader has gone."""
from __future__ import annotations

import fcntl
import os
import subprocess
import sys

import pytest
import yaml
from fixtures.budgets import within
from fixtures.console import untimed
from fixtures.paths import ROOT, TESTS

from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.exit_codes import PIPE_CLOSED

CHILD = TESTS / "fixtures" / "cli_child.py"
EXAMPLES = ROOT / "rocoma_can" / "examples"
#: a command's whole life here: imports, a manager or drives beside it, its answer
BUDGET = within(30.0)


def run_child(args: list[str], stdout: int, manager: str | None = None,
              drives: str | None = None) -> tuple[int, str]:
    """(exit code, stderr) of ``rocoma-can ARGS`` with ``stdout`` (a file descriptor)."""
    own = (["--manager", manager] if manager else []) + (["--drives", drives] if drives
                                                         else [])
    done = subprocess.run([sys.executable, str(CHILD), *own, "--", *args], stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=BUDGET)
    return done.returncode, done.stderr


def gone_reader() -> int:
    """A pipe's writing end whose reader has gone: the first write fails (EPIPE)."""
    read, write = os.pipe()
    os.close(read)
    return write


def manager_verb(channel: str, *verb: str) -> list[str]:
    return [*verb, "--interface", "virtual", "--channel", channel]


@pytest.mark.parametrize("verb", [
    ["--help"], ["--version"], ["run", "--help"],
    ["check-config", str(EXAMPLES / "robot_can0.yaml"), "--drives"],
    ["status"], ["status", "--json"], ["status", "--watch", "--duration", "2"], ["list"],
    ["switch", "pd"], ["estop"]],
    ids=lambda verb: " ".join(verb[:2]).replace(str(EXAMPLES) + "/", ""))
def test_a_reader_gone_ends_the_verb_quietly_with_141(verb, virtual_channel):
    needs_manager = verb[0] in ("status", "list", "switch", "estop")
    args = manager_verb(virtual_channel, *verb) if needs_manager else verb
    stdout = gone_reader()
    try:
        code, err = run_child(args, stdout, manager=virtual_channel if needs_manager else None)
    finally:
        os.close(stdout)
    assert (code, err) == (PIPE_CLOSED, ""), err


def test_scan_with_its_reader_gone_ends_quietly_with_141(virtual_channel):
    """scan reads the bus first (its own OSError handling: a bus it cannot send on is a
    usage error, exit 2); a reader gone is not that."""
    stdout = gone_reader()
    try:
        code, err = run_child(["scan", "--interface", "virtual", "--channel", virtual_channel],
                              stdout, drives=f"{virtual_channel}:2")
    finally:
        os.close(stdout)
    assert (code, err) == (PIPE_CLOSED, ""), err


def test_a_reader_that_reads_the_first_lines_and_goes(tmp_path):
    """``| head -3`` of a long result: the reader takes some lines and closes while the
    verb still writes (the pipe made one page small, so the rest cannot all wait in it)."""
    read, write = os.pipe()
    fcntl.fcntl(write, fcntl.F_SETPIPE_SZ, 4096)
    child = subprocess.Popen([sys.executable, str(CHILD), "--", "check-config",
                              str(EXAMPLES / "robot_can0.yaml"), "--drives"],
                             stdout=write, stderr=subprocess.PIPE, text=True)
    os.close(write)
    with os.fdopen(read, "rb") as reader:
        head = reader.read(200)
    try:
        _, err = child.communicate(timeout=BUDGET)
    finally:
        child.kill()
    assert head.startswith(str(EXAMPLES / "robot_can0.yaml").encode() + b": ok: 12 drives")
    assert (child.returncode, err) == (PIPE_CLOSED, ""), err


def test_the_demo_whose_reader_goes_while_its_threads_print_ends_quietly():
    """``rocoma-can demo | head -2``: the demo's lines come from its operator's and its
    status threads and the recorder's reply reader too; each of them ended in a
    BrokenPipeError traceback of its thread once the reader had gone."""
    read, write = os.pipe()
    fcntl.fcntl(write, fcntl.F_SETPIPE_SZ, 4096)
    child = subprocess.Popen([sys.executable, str(CHILD), "--", "demo", "--duration", "1",
                              "--drives", "2", "--no-record"],
                             stdout=write, stderr=subprocess.PIPE, text=True)
    os.close(write)
    with os.fdopen(read, "rb") as reader:
        head = reader.readline()
    try:
        _, err = child.communicate(timeout=BUDGET)
    finally:
        child.kill()
    assert head.startswith(b"rocoma-can demo: 2 simulated drives"), head
    assert (child.returncode, err) == (PIPE_CLOSED, ""), err


def test_run_goes_on_when_its_stdout_closes_and_says_so_on_stderr(tmp_path, virtual_channel):
    """A robot is not stopped because the reader of its log went away (a `| tee` that
    ended): the run goes on to its end, says once where its lines go, writes them there,
    and exits with its own code."""
    cfg = demo_config(virtual_channel, drives=2, rate=100)
    cfg["bus"]["interface"] = "virtual"
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    stdout = gone_reader()
    try:
        code, err = run_child(["run", str(path), "--duration", "2", "--no-flight"], stdout,
                              drives=f"{virtual_channel}:2")
    finally:
        os.close(stdout)
    lines = untimed(err)
    assert lines[0] == ("rocoma-can: warning: stdout was closed (its reader ended); this run "
                        "goes on, its lines go to stderr from now on"), lines
    assert lines[1].startswith("rocoma-can: running 2 drives at 100 Hz"), lines
    assert lines[-1].startswith("rocoma-can: stopped (duration reached); cycles "), lines
    assert code == 0, err
