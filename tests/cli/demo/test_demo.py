"""rocoma_can/cli/demo/ (walkthrough.py, steps.py, report.py, config.py): the embedded demo
runs its whole walk-through (shortened) and says so with exit code 0."""
from __future__ import annotations

import logging
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fixtures.paths import ROOT, TESTS

from rocoma_can.cli.demo.command import path_hint
from rocoma_can.cli.demo.walkthrough import DemoOptions, Walkthrough
from rocoma_can.cli.main import main


def test_demo_walk_through_passes():
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=3, rate=100.0, duration=3.0), out=lines.append).run()
    assert report.ok, "\n".join(lines)
    names = [s.name for s in report.steps]
    assert names[0] == "bring-up" and names[-1] == "loop stop -> torque-off frames"
    assert any("failproof" in n for n in names) and any("recovery" in n for n in names)
    # a fault or e-stop step passes only once the loop's watch has recorded the change
    # whose latency it reports: one per such step, however late the watch ran
    assert [what.split(" -> ")[1] for what, _, _ in report.latencies] \
        == ["EMERGENCY", "FAILPROOF", "EMERGENCY"]
    assert all(took >= 0 and cycles >= 1 for _, took, cycles in report.latencies)
    assert lines[-1] == "demo passed"


def test_every_latency_is_reported_when_the_watch_runs_late(monkeypatch):
    """The flaky CI run, made certain: the loop's watch records a state change a few cycles
    after the manager's state shows it (as a loaded host may schedule it). Each fault and
    e-stop step still reports its latency."""
    from rocoma_can.cli.demo.steps import StateWatch
    rate = 100.0
    record = StateWatch.__call__

    def late(self, now: float) -> None:
        if self.runtime is not None and int(self.runtime.loop.last_state) != self.state:
            time.sleep(5 / rate)  # five cycles behind the manager's state
        record(self, now)

    monkeypatch.setattr(StateWatch, "__call__", late)
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=3, rate=rate, duration=3.0, record=None),
                         out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert len(report.latencies) == 3


def test_demo_on_several_buses_passes():
    """Six drives on three buses: the faults go to the first bus, the loop's stop sends
    torque-off frames to every drive on every bus."""
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=6, rate=100.0, duration=3.0, buses=3),
                         out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert "3 inproc buses" in lines[0]
    assert report.steps[-1].detail.endswith("6/6 drives' RPDOs on 3 buses")


def test_demo_on_python_cans_virtual_bus_passes():
    """The demo is not tied to the in-process bus: python-can's virtual runs it too."""
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=2.0, interface="virtual"),
                         out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert "virtual bus" in lines[0]


def test_demo_cli_rejects_bad_options(capsys):
    assert main(["demo", "--drives", "0"]) == 2
    assert main(["demo", "--drives", "6", "--buses", "4"]) == 2
    assert "--buses 1..drives/2" in capsys.readouterr().out


def test_demo_records_its_run_and_plots_it(tmp_path):
    """What `rocoma-can demo` does by default: the run recorded (every cycle, event and
    frame), drawn, and both paths said."""
    from rocoma_can.record.plot import load_trace
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=2.0, record=tmp_path),
                         out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert report.recording == tmp_path / "trace.mcap"
    assert report.plot == tmp_path / "demo.png"
    assert report.plot.read_bytes()[:4] == b"\x89PNG"
    assert f"plot: {report.plot}" in lines and any(
        line.startswith(f"recording: {report.recording}") for line in lines)
    causes = [cause for _, cause in load_trace(report.recording).estops]
    assert any("CAN e-stop from 0x0A0" in c for c in causes), causes  # the walk-through's
    assert len(list(tmp_path.glob("*.log"))) == 1  # the bus's frames, candump
    # the walk-through's recovery (SDO 0x2113), as an event and a log line: started, then
    # done, and the latch cleared in between
    from rocoma_can.record.trace import read_messages
    messages = list(read_messages(str(report.recording)))
    told = [m["cause"].split(":")[0] for topic, _, m in messages
            if topic == "/rocoma/event" and m["kind"] == "recovery"]
    assert told == ["started", "done"], told
    logged = [m["message"] for topic, _, m in messages if topic == "/rocoma/log"]
    started = next(k for k, line in enumerate(logged) if line.startswith("recovery started"))
    done = next(k for k, line in enumerate(logged) if line.startswith("recovery done"))
    assert any("emergency stop cleared" in line for line in logged[started:done]), logged


def _writer_processes() -> list[int]:
    """This process's recording writers (record/recorder.py starts one per run)."""
    found = []
    for task in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{task}/children") as children:
            for pid in children.read().split():
                try:
                    with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
                        if b"rocoma_can.record.writer" in cmdline.read():
                            found.append(int(pid))
                except OSError:  # ended meanwhile
                    pass
    return found


def test_a_recording_that_stopped_is_said_and_fails_the_demo(tmp_path):
    """The writer process killed mid-walk-through (the OOM killer; a full disk ends the
    recording alike): the demo does not claim "every cycle and frame" of a recording with
    a hole, says where and why it stopped, and exits 1 as run does (it said "demo passed",
    exit 0)."""
    import signal
    lines: list[str] = []

    def out(line: str) -> None:
        lines.append(line)
        if line.startswith("ok  switch to pd"):  # the first step after bring-up
            for pid in _writer_processes():
                os.kill(pid, signal.SIGKILL)

    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=2.0, record=tmp_path),
                         out=out).run()
    assert any(line.startswith("ok  switch to pd") for line in lines), "\n".join(lines)
    failed = [step for step in report.steps if not step.ok]
    assert [step.name for step in failed] == ["recording"], "\n".join(lines)
    assert failed[0].detail.startswith("the recording's writer process ended (exit code -9)")
    said = [line for line in lines if line.startswith("recording: ")]
    assert said == [f"recording: {tmp_path / 'trace.mcap'} stopped early, what was written "
                    f"stays: {failed[0].detail}"], said
    assert not report.ok


def test_demo_cli_says_when_it_cannot_record(tmp_path, capsys):
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    assert main(["demo", "--drives", "2", "--record", str(blocked / "rec")]) == 2
    assert "cannot create the directory" in capsys.readouterr().out


EDS = TESTS / "fixtures" / "eds"


def test_demo_duration_is_the_walk_throughs_length():
    """--duration is from bring-up to the loop's stop: the pauses fill it (they used to be
    a tenth of it each, and 60 s ran 28)."""
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=5.0), out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert report.walk_time >= 5.0
    assert f"  {'walk-through':28s} {report.walk_time:.1f} s" in lines


def test_demo_cli_groups_the_files_notes_and_says_how_to_get_the_command(
        tmp_path, monkeypatch, capsys, caplog):
    """`bash tools/demo` runs the venv's rocoma-can without the venv on PATH: the demo's
    last line says how to get the command. What the file degrades is one line per object
    naming the drives, and not also the hardware's log line per drive."""
    monkeypatch.setenv("PATH", str(tmp_path))  # no rocoma-can on it, as after tools/demo
    monkeypatch.chdir(Path(sys.prefix).parent)
    with caplog.at_level(logging.WARNING):
        assert main(["demo", "--eds", str(EDS / "minimal.eds"), "--drives", "3",
                     "--duration", "2", "--no-record", "--no-flight"]) == 0
    out = capsys.readouterr().out.splitlines()
    notes = [line for line in out if line.startswith("  note: joint")]
    assert notes == [
        "  note: joint1, joint2, joint3: no 0x6077: torque feedback off (JointState.torque "
        "stays 0)",
        "  note: joint1, joint2, joint3: no 0x608F: increments_per_rev comes from the config "
        "alone (the drive cannot confirm it)",
        "  note: joint1, joint2, joint3: no 0x6091: gear_ratio comes from the config alone "
        "(the drive cannot confirm it)"]
    assert [r.getMessage() for r in caplog.records] == []
    assert out[-2:] == [
        "demo passed",
        f"rocoma-can: not on PATH; for the README's commands: . "
        f"{Path(sys.prefix).name}/bin/activate (or pip install -e "
        "'.[record,plot,live,zenoh,foxglove,ros2]' from a checkout)"]


def test_no_path_hint_when_the_command_is_found(tmp_path, monkeypatch):
    command = tmp_path / "rocoma-can"
    command.write_text("#!/bin/sh\n")
    command.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    assert path_hint() is None


def test_the_path_hint_installs_what_the_readme_uses(tmp_path, monkeypatch):
    """The hint's install has every extra the README's commands need (each it names in a
    ``pip install``): the README's next steps include ``run --foxglove``, which the
    hint's install once lacked."""
    import re
    tomllib = pytest.importorskip("tomllib")  # Python 3.11
    root = ROOT
    readme = (root / "README.md").read_text()
    used = {extra for group in re.findall(r"pip install[^`]*?\[([\w,]+)\]", readme)
            for extra in group.split(",")}
    monkeypatch.setenv("PATH", str(tmp_path))
    hint = path_hint()
    assert hint is not None
    given = set(re.search(r"pip install -e '\.\[([\w,]+)\]'", hint).group(1).split(","))
    assert "foxglove" in used and used <= given, (used, hint)
    defined = tomllib.loads((root / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]
    assert given <= set(defined)


def test_demo_says_once_what_is_wrong_with_a_file(tmp_path, capsys):
    """A file no drive can run on is one line about the file: not one per drive, and not
    prefixed "demo: demo:"."""
    text = (EDS / "minimal.eds").read_text()
    head, tail = text.split("[1017]", 1)
    no_heartbeat = tmp_path / "no_heartbeat.eds"
    no_heartbeat.write_text(head + "[1017]" + tail.replace("AccessType=rw", "AccessType=ro", 1))
    assert main(["demo", "--eds", str(no_heartbeat), "--drives", "3", "--no-record"]) == 2
    assert capsys.readouterr().out.splitlines() == [
        f"demo: --eds: {no_heartbeat} has neither a writable heartbeat producer (0x1017) "
        "nor node guarding (0x100C/0x100D): rocoma-can must see every drive's life"]


def test_demo_config_problems_are_not_prefixed_twice(capsys):
    assert main(["demo", "--drives", "2", "--no-record", "--zenoh-listen", "bogus"]) == 2
    assert capsys.readouterr().out.splitlines() == [
        "demo: zenoh.listen: expected Zenoh endpoints like tcp/192.168.1.10:7447, got "
        "['bogus']"]


def test_each_estop_of_the_demo_leaves_a_flight_record(tmp_path):
    """As `run` does: the walk-through's e-stops leave flight records, each path said as it
    is written; together they hold every e-stop's cause (e-stops within half the demo's
    window share a record), and the demo's window is the one recorded."""
    from rocoma_can.cli.demo.walkthrough import FLIGHT_SECONDS
    from rocoma_can.record.plot import load_trace
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=2.0, record=None,
                                     flight=tmp_path / "flight"), out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert report.flight_records, "\n".join(lines)
    assert sorted(report.flight_records) == sorted((tmp_path / "flight").glob("*.mcap"))
    said = [line for line in lines if line.startswith("rocoma-can demo: flight record (")]
    assert [line.rsplit(": ", 1)[1] for line in said] == \
        [str(p) for p in report.flight_records]
    assert f"flight records: {len(report.flight_records)} in {tmp_path / 'flight'}" in lines
    causes = [cause for p in report.flight_records for _, cause in load_trace(p).estops]
    assert any("CAN e-stop from 0x0A0" in c for c in causes), causes
    assert any("EMCY" in c for c in causes), causes  # the drive faults the demo trips
    first = load_trace(report.flight_records[0])
    assert first.time[-1] - first.time[0] <= FLIGHT_SECONDS + 0.5  # its window, not run's


def test_a_run_that_overruns_points_at_doctor_timing(monkeypatch):
    """Every cycle made to overrun (the loop's watch sleeps 1.5 periods after each): the
    summary says how to measure the host's share of them."""
    from rocoma_can.cli.demo.steps import StateWatch
    rate = 100.0
    record = StateWatch.__call__

    def slow(self, now: float) -> None:
        time.sleep(1.5 / rate)
        record(self, now)

    monkeypatch.setattr(StateWatch, "__call__", slow)
    lines: list[str] = []
    Walkthrough(DemoOptions(drives=3, rate=rate, duration=2.0, record=None), out=lines.append).run()
    at = next(k for k, line in enumerate(lines) if "overruns (past their period)" in line)
    assert "rocoma-can doctor --timing" in lines[at + 1]


def test_the_doctor_hint_comes_above_a_thousandth_of_the_cycles():
    from rocoma_can.cli.demo.report import host_hint
    from rocoma_can.runtime.loop import TimingSummary

    def timing(overruns: int) -> TimingSummary:
        return TimingSummary(10_000, overruns, 0, 1e-3, 2e-3, 1e-3, 1e-4, 5e-4)

    assert host_hint(timing(10)) is None  # 0.1 %: issue 36's target, met
    assert "doctor --timing" in (host_hint(timing(11)) or "")


def test_the_demo_runs_its_loop_at_the_priority_asked_and_gives_the_thread_back(monkeypatch):
    """``--priority``: the loop's thread (the one calling Walkthrough.run) runs SCHED_FIFO at it
    for the walk-through, seen from the loop's own cycles, and is normal again after."""
    from rocoma_can.cli.demo.steps import StateWatch
    if os.geteuid() != 0 and resource.getrlimit(resource.RLIMIT_RTPRIO)[0] < 10:
        pytest.skip("no CAP_SYS_NICE nor an rtprio limit here: the refusal test covers it")
    seen: set[tuple[int, int]] = set()
    watch = StateWatch.__call__

    def policy(self, now: float) -> None:  # the loop's on_cycle, on the loop's thread
        seen.add((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))
        watch(self, now)

    monkeypatch.setattr(StateWatch, "__call__", policy)
    before = os.sched_getscheduler(0)
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=3, rate=100.0, duration=2.0, priority=10),
                         out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert seen == {(os.SCHED_FIFO, 10)}
    assert os.sched_getscheduler(0) == before == os.SCHED_OTHER
    assert any(line.split() == ["loop", "priority", "SCHED_FIFO", "10"] for line in lines)


def test_a_refused_priority_is_said_and_the_demo_runs_on(tmp_path):
    """Without CAP_SYS_NICE (dropped from the process as root; none to begin with
    otherwise) the kernel refuses SCHED_FIFO: the summary says so and the demo passes."""
    cmd = [sys.executable, "-m", "rocoma_can", "demo", "--drives", "3", "--rate", "100",
           "--duration", "2", "--no-record", "--no-flight", "--priority", "20"]
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("setpriv (util-linux) is needed to drop CAP_SYS_NICE as root")
        cmd = ["setpriv", "--bounding-set", "-sys_nice", "--inh-caps", "-sys_nice", *cmd]
    elif resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= 20:
        pytest.skip("an rtprio limit lets this user have SCHED_FIFO 20")
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    line = next(line for line in done.stdout.splitlines() if "loop priority" in line)
    assert "normal: SCHED_FIFO priority 20 not set" in line and "CAP_SYS_NICE" in line
    assert "demo passed" in done.stdout.splitlines()


def test_the_demo_cli_refuses_a_priority_out_of_range(capsys):
    for bad in ("0", "100", "x", "1.5"):
        with pytest.raises(SystemExit) as exited:
            main(["demo", "--priority", bad])
        assert exited.value.code == 2
        assert "expected a real-time priority 1..99" in capsys.readouterr().err


@pytest.mark.parametrize("after", ["bring-up", "switch pd -> trajectory"])
def test_an_operators_estop_ends_the_walk_through_and_is_never_undone(virtual_channel,
                                                                      after):
    """An e-stop from outside the walk-through (here `rocoma-can estop`'s SDO write, as
    Foxglove's or Zenoh's e-stop service would) ends it at its next step: the robot stays
    stopped (no clear, recovery or switch after it), the stop and the loop's torque-off are
    reported, and the demo passes: the manager obeyed the operator. After bring-up the stop
    comes just before the walk-through's clear and switch: the demo reads the manager's
    request at once (its event comes a cycle later), so neither goes out."""
    import can

    from rocoma_can.cli.demo.config import MANAGER_ID
    from rocoma_can.node.client import ManagerClient
    from rocoma_can.node.objects import ESTOP

    lines: list[str] = []

    def out(line: str) -> None:
        lines.append(line)
        if line.startswith(f"ok  {after}"):  # the operator presses e-stop
            with can.Bus(interface="inproc", channel=virtual_channel,
                         ignore_config=True) as bus, ManagerClient(bus, MANAGER_ID) as c:
                c.write(ESTOP, 1)

    report = Walkthrough(DemoOptions(drives=3, rate=100.0, duration=3.0, channel=virtual_channel),
                         out=out).run()
    assert report.ok, "\n".join(lines)
    names = [s.name for s in report.steps]
    done = ["bring-up"] if after == "bring-up" else [
        "bring-up", "switch to pd (SDO 0x2100)", "switch pd -> trajectory (swap state)"]
    assert names == [*done, "walk-through", "loop stop -> torque-off frames"], names
    assert "SDO e-stop (0x2110)" in report.steps[-2].detail
    assert not any(line.startswith(("ok  recovery", "ok  fault", "FAILED")) for line in lines)
    assert lines[-1] == "demo passed"


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_ends_the_walk_through_as_interrupted(virtual_channel, signum, capsys):
    """Ctrl-C or SIGTERM in the middle of the walk-through: the loop stops with its
    torque-off; the walk-through commanded on (a fault, a recovery, a switch into a stopped
    loop), then called every step after it FAILED, the torque-off check too ("before the
    probes opened"), exit 1. It ends where the signal came: the steps after it not run and
    not judged, the check said skipped and why, "demo interrupted", exit 130."""
    import threading

    main_thread = threading.main_thread().ident
    assert main_thread is not None
    lines: list[str] = []

    def out(line: str) -> None:
        lines.append(line)
        if line.startswith("ok  switch to pd"):
            signal.pthread_kill(main_thread, signum)  # the loop's handler takes it

    report = Walkthrough(DemoOptions(drives=3, rate=100.0, duration=3.0, channel=virtual_channel),
                         out=out).run()
    assert report.interrupted == f"signal {signum.name}" and not report.ok
    names = [s.name for s in report.steps]
    assert names == ["bring-up", "switch to pd (SDO 0x2100)", "walk-through",
                     "loop stop -> torque-off frames"], "\n".join(lines)
    assert all(s.ok for s in report.steps), "\n".join(lines)
    assert not any(line.startswith("FAILED") for line in lines), "\n".join(lines)
    assert f"stop walk-through: cut short: the loop stopped (signal {signum.name}); the " \
           "steps after it not run" in lines, "\n".join(lines)
    assert lines[-1] == f"demo interrupted (signal {signum.name}) after 2 steps of the " \
                        "walk-through"
    assert report.steps[-1].detail.startswith("skipped: ") \
        and report.steps[-1].detail.endswith("the manager ended in FAILPROOF")


def test_the_demo_cli_exits_130_when_stopped_by_sigterm(tmp_path):
    """As a user's Ctrl-C or a supervisor's SIGTERM reaches it: the documented exit code for
    an interrupted command, the verdict line saying so."""
    from fixtures.running import DEMO_WAIT

    from rocoma_can.cli.exit_codes import INTERRUPTED
    cmd = [sys.executable, "-m", "rocoma_can", "demo", "--drives", "3", "--rate", "100",
           "--duration", "6", "--no-record", "--flight-dir", str(tmp_path)]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True) as demo:
        assert demo.stdout is not None
        lines = []
        for line in demo.stdout:
            lines.append(line.rstrip("\n"))
            if line.startswith("ok  switch to pd"):
                demo.send_signal(signal.SIGTERM)
        assert demo.wait(DEMO_WAIT) == INTERRUPTED, "\n".join(lines)
    assert "demo interrupted (signal SIGTERM) after 2 steps of the walk-through" in lines
