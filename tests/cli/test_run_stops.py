"""rocoma_can/cli/run.py (``run``): a stop signal (Ctrl-C, SIGTERM) for ``rocoma-can run`` at
each phase of a run has one outcome, said in one line (docs/cli.md, "Stopping run"):

* before bring-up (reading the config, opening the buses, starting the recorder's writer):
  ``interrupted (SIGINT) before bring-up: nothing was sent to the drives``, exit 130;
* during bring-up: the loop's torque-off, ``stopped (signal SIGINT) during bring-up,
  torque-off sent; not brought up: ...``, exit 130;
* running: the loop's torque-off, ``stopped (signal SIGINT); cycles ...``, exit 0;
* closing (a second signal after the torque-off): test_record_interrupts.py.

No phase leaves a flight record: a stop the operator asked for is no fault, and the
writer is told the run ends (it wrote "the manager's process ended without closing" when
a Ctrl-C cut the writer's start short). Each run is a real ``rocoma-can run`` in a process
of its own, the signal sent at a point of the phase the test makes sure it has reached.
"""
from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from fixtures.budgets import within
from fixtures.configs import nobody_answers
from fixtures.console import untimed
from fixtures.paths import TESTS
from fixtures.processes import blocked_in, gone, writer_of
from fixtures.running import DEMO_WAIT, wait_for

from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.exit_codes import INTERRUPTED, OK

CHILD = TESTS / "fixtures" / "cli_child.py"
#: a run's start here: the interpreter, the imports, the writer process's own
START = within(20.0)


def _stays_blocked_in(pid: int, where: str, looks: int = 5) -> bool:
    """Blocked there at ``looks`` looks 20 ms apart: a write to a full pipe stays, one that
    goes through (the writer process's set-up on its own pipe) does not."""
    for look in range(looks):
        if not blocked_in(pid, where):
            return False
        if look < looks - 1:
            time.sleep(0.02)
    return True


class Run:
    """``rocoma-can run`` in a process of its own (beside simulated drives when asked),
    its stdout and stderr read as they come."""

    def __init__(self, args: list[str], drives: str | None = None,
                 stdout: int | None = None) -> None:
        own = ["--drives", drives] if drives else []
        self.process = subprocess.Popen(
            [sys.executable, str(CHILD), *own, "--", "run", *args],
            stdout=subprocess.PIPE if stdout is None else stdout, stderr=subprocess.PIPE)
        self.out: list[bytes] = []
        self.err: list[bytes] = []
        self._readers = [threading.Thread(target=self._read, args=(stream, into), daemon=True)
                         for stream, into in ((self.process.stdout, self.out),
                                              (self.process.stderr, self.err))
                         if stream is not None]
        for reader in self._readers:
            reader.start()

    @staticmethod
    def _read(stream, into: list[bytes]) -> None:
        for line in stream:
            into.append(line)

    def said(self, text: str) -> bool:
        return any(text.encode() in line for line in self.out)

    def end(self, timeout: float) -> tuple[int, list[str], list[str]]:
        """The exit code and the lines of stdout and stderr, without their time."""
        try:
            code = self.process.wait(timeout)
        finally:
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait(DEMO_WAIT)
        for reader in self._readers:
            reader.join(DEMO_WAIT)
        return (code, untimed(b"".join(self.out).decode()),
                untimed(b"".join(self.err).decode()))


@pytest.fixture
def flight(tmp_path: Path) -> Path:
    return tmp_path / "flight"


def _bench(tmp_path: Path, channel: str) -> Path:
    """Two simulated drives' config on ``channel`` (the child's --drives)."""
    cfg = demo_config(channel, drives=2, rate=100)
    cfg["bus"]["interface"] = "virtual"
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_ctrl_c_while_the_config_is_read_says_nothing_was_sent(tmp_path):
    """Before bring-up, at its first step: the config (a FIFO that nobody writes stands
    for a slow file system) is being read."""
    fifo = tmp_path / "robot.yaml"
    os.mkfifo(fifo)
    run = Run([str(fifo), "--no-flight"])
    wait_for(lambda: blocked_in(run.process.pid, "partner"), "the config's open", START)
    run.process.send_signal(signal.SIGINT)
    code, out, err = run.end(DEMO_WAIT)
    assert (code, out, err) == (INTERRUPTED, [], [
        "rocoma-can: error: interrupted (SIGINT) before bring-up: nothing was sent to the "
        "drives"])


def test_ctrl_c_before_bring_up_ends_the_writer_without_a_flight_record(
        tmp_path, virtual_channel, flight):
    """Before bring-up, at its last step: the buses are open and the recorder's writer
    runs; the run's first line is being written (a reader that takes nothing yet: the
    pipe is full)."""
    read, write = os.pipe()
    fcntl.fcntl(write, fcntl.F_SETPIPE_SZ, 4096)
    os.write(write, b"\n" * 4096)
    run = Run([str(_bench(tmp_path, virtual_channel)), "--flight-dir", str(flight)],
              drives=f"{virtual_channel}:2", stdout=write)
    os.close(write)
    try:
        wait_for(lambda: _stays_blocked_in(run.process.pid, "pipe_write"), "the first line",
                 START)
        writer = writer_of(run.process.pid)
        run.process.send_signal(signal.SIGINT)
        with os.fdopen(read, "rb") as reader:  # the rest, now the run may go on
            out = reader.read().decode().strip("\n")
    finally:
        code, _, err = run.end(DEMO_WAIT)
    # the line the signal cut short may be lost with the write (the interpreter drops
    # what a write interrupted by a signal's exception held): there is no other line
    assert untimed(out) in ([], ["rocoma-can: running 2 drives at 100 Hz on virtual:"
                                 f"{virtual_channel}, manager node 100 (Ctrl-C / SIGTERM: "
                                 "torque-off, then exit)"]), out
    assert (code, err) == (INTERRUPTED, [
        "rocoma-can: error: interrupted (SIGINT) before bring-up: nothing was sent to the "
        "drives"])
    wait_for(lambda: gone(writer), "the writer ended", DEMO_WAIT)
    assert not flight.exists() or not [p for p in flight.iterdir()
                                        if not p.name.startswith(".")]


def test_ctrl_c_during_bring_up_torques_off_and_exits_130(tmp_path, flight):
    """Its drive does not answer yet (a long SDO timeout: bring-up takes seconds). The stop
    comes as soon as run says its state: from that line on, a stop is the loop's (on a
    loaded machine one that came before the loop had started was an interrupt: exit 130
    without the torque-off line)."""
    path = nobody_answers(tmp_path)
    cfg = yaml.safe_load(path.read_text())
    cfg["supervision"]["sdo_timeout"] = 5.0
    path.write_text(yaml.safe_dump(cfg))
    run = Run([str(path), "--flight-dir", str(flight)])
    wait_for(lambda: run.said("state FAILPROOF"), "the run started", START)
    run.process.send_signal(signal.SIGINT)
    code, out, err = run.end(DEMO_WAIT)
    assert code == INTERRUPTED, (out, err)
    assert out[-2] == "rocoma-can: torque-off (FAILPROOF): loop stopping: signal SIGINT"
    # (its phase: waiting for the boot-up, or asking 0x1000; no cycle may have run yet)
    assert out[-1].startswith("rocoma-can: stopped (signal SIGINT) during bring-up, "
                              "torque-off sent; not brought up: j1 ("), out
    assert err == []  # no "bring-up did not finish": the operator stopped it
    assert not flight.exists() or not list(flight.glob("*.mcap"))


def test_a_stop_signal_right_after_the_state_line_is_the_loops(tmp_path, capfd):
    """The moment between run's state line and the loop's start, made exact: the signal is
    raised as the line is logged (this process, main() on its main thread). It is the loop's
    stop with its torque-off, not an interrupt said as "while closing, after the
    torque-off" (no torque-off had been sent; seen on a loaded machine)."""
    import logging

    from rocoma_can.cli.main import main
    from rocoma_can.cli.run import AUDIT

    class SignalAtState(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.getMessage().startswith("state FAILPROOF"):
                os.kill(os.getpid(), signal.SIGINT)
    path = nobody_answers(tmp_path)
    cfg = yaml.safe_load(path.read_text())
    cfg["supervision"]["sdo_timeout"] = 5.0
    path.write_text(yaml.safe_dump(cfg))
    trigger = SignalAtState()
    logging.getLogger(AUDIT).addHandler(trigger)
    try:
        code = main(["run", str(path), "--no-flight"])
    finally:
        logging.getLogger(AUDIT).removeHandler(trigger)
    said = untimed(capfd.readouterr().out)
    assert code == INTERRUPTED, said
    assert said[-2] == "rocoma-can: torque-off (FAILPROOF): loop stopping: signal SIGINT"
    assert said[-1].startswith("rocoma-can: stopped (signal SIGINT) during bring-up, "
                               "torque-off sent; not brought up: j1 ("), said


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_a_stop_signal_while_running_torques_off_and_exits_0(tmp_path, virtual_channel,
                                                            flight, stop):
    run = Run([str(_bench(tmp_path, virtual_channel)), "--flight-dir", str(flight)],
              drives=f"{virtual_channel}:2")
    wait_for(lambda: run.said("bring-up finished"), "the drives ready", START)
    time.sleep(0.2)
    run.process.send_signal(stop)
    code, out, err = run.end(DEMO_WAIT)
    assert code == OK, (out, err)
    assert out[-2] == f"rocoma-can: torque-off (FAILPROOF): loop stopping: signal {stop.name}"
    assert out[-1].startswith(f"rocoma-can: stopped (signal {stop.name}); cycles "), out
    assert err == []
    assert not flight.exists() or not list(flight.glob("*.mcap"))


@pytest.mark.parametrize("cut", ["fleet_from_args", "ros2_from_args", "recording_available"])
def test_ctrl_c_between_the_config_and_the_buses_says_nothing_was_sent(
        tmp_path, virtual_channel, capsys, monkeypatch, cut):
    """Before bring-up, between its steps (the command's own imports, the Zenoh and ROS 2
    options, the recorder's look for mcap): the same line as at its first and last step,
    not main()'s bare ``interrupted (SIGINT)``."""
    from rocoma_can.cli import run as run_verb
    from rocoma_can.cli.main import main

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(run_verb, cut, interrupted)
    assert main(["run", str(_bench(tmp_path, virtual_channel))]) == INTERRUPTED
    captured = capsys.readouterr()
    assert (untimed(captured.out), untimed(captured.err)) == ([], [
        "rocoma-can: error: interrupted (SIGINT) before bring-up: nothing was sent to the "
        "drives"])
