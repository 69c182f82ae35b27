"""rocoma_can/record/recording.py, flight.py, recorder.py, record/plot.py: the flight recorder's
dump on an e-stop, `run --record`'s MCAP trace with every cycle, export to CSV, and an unwritable
place that is an error said clearly, never a stop of the loop (raw CAN files: test_can_log.py;
foreign and damaged traces: test_trace.py)."""
from __future__ import annotations

import csv
import json
import logging
import os
import re
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import numpy as np
import pytest
import yaml
from fixtures.running import (
    BENCH_RATE,
    DEMO_RUN,
    DEMO_WAIT,
    run_operated,
    switch_and_stop,
    wait_for,
)

from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.main import main
from rocoma_can.record.recorder import STATUS_PERIOD
from rocoma_can.record.recording import slug as _slug
from rocoma_can.record.trace import read_messages
from rocoma_can.runtime import Runtime

RATE = BENCH_RATE


@pytest.fixture
def config(demo_bench):
    return demo_bench[0]


def test_an_estop_dumps_the_last_seconds_of_signals_and_frames(demo_bench, tmp_path):
    config, segment = demo_bench
    announced: list[str] = []
    with Runtime(config, flight=str(tmp_path / "flight"), flight_seconds=1.0,
                 announce=announced.append) as rt:
        run_operated(rt, switch_and_stop(rt, 1.5, fault=segment.drives[1].trip_fault,
                                         settle=0.5))
        assert rt.flight is not None
    dumps = sorted((tmp_path / "flight").iterdir())
    assert len(dumps) == 2, dumps  # the e-stop, and the shutdown after it
    first = dumps[0]
    assert announced and str(first) in announced[0]
    messages = list(read_messages(str(first)))
    cycles = [(t, m) for topic, t, m in messages if topic == "/rocoma/cycle"]
    frames = [(t, m) for topic, t, m in messages if topic.startswith("/can/")]
    assert cycles and frames
    span = (cycles[-1][0] - cycles[0][0]) / 1e9
    assert span >= 0.9  # the last flight_seconds before the e-stop
    assert cycles[-1][1]["state"] in ("EMERGENCY", "FAILPROOF")
    assert cycles[0][1]["state"] == "OK"
    assert len(cycles[0][1]["position"]) == 2
    assert {m["id"] for _, m in frames} >= {0x181, 0x182, 0x201, 0x202, 0x080}
    events = [m for topic, _, m in messages if topic == "/rocoma/event"]
    stops = [m for m in events if m["kind"] == "emergency_stop"]
    assert len(stops) == 1 and "(node 1)" in stops[0]["cause"], events
    assert stops[0]["state"] in ("EMERGENCY", "FAILPROOF")


def test_an_estop_storm_is_a_few_flight_records_not_one_per_estop(config, tmp_path):
    """A held e-stop button repeats its frame, and each is an e-stop event (in FAILPROOF
    too): one file each would fill the disk and compete with the loop for the CPU. The
    first is written at once, the rest within half a window go into one more file, and
    the shutdown writes the last."""
    storm = 50
    with Runtime(config, flight=str(tmp_path / "flight"), flight_seconds=1.0) as rt:
        def operate() -> None:
            deadline = time.monotonic() + DEMO_WAIT
            while rt.loop.stats.cycles < 10 and time.monotonic() < deadline:
                time.sleep(0.01)
            for _ in range(storm):  # back to back: a loaded machine cannot stretch it
                rt.manager.emergency_stop("storm")  # past the recorder's hold-off
            time.sleep(0.2)
            rt.loop.stop("test")
        worker = threading.Thread(target=operate)
        worker.start()
        rt.run(duration=DEMO_RUN, signals=False)
        worker.join(DEMO_WAIT)
    dumps = sorted((tmp_path / "flight").iterdir())
    assert 2 <= len(dumps) <= 3, dumps  # first, (the rest together,) shutdown
    assert any("more" in d.name for d in dumps), dumps  # the storm, merged


def test_the_status_report_goes_into_the_recording_and_the_flight_record(demo_bench,
                                                                         tmp_path):
    """/rocoma/status (the live view's status panel: cycle statistics, each bus's load and
    errors, the drives) is in the files too, once every STATUS_PERIOD: the recording has
    each report once, a flight record those of its window."""
    config, segment = demo_bench
    with Runtime(config, record=str(tmp_path / "rec"), flight=str(tmp_path / "flight"),
                 flight_seconds=3 * STATUS_PERIOD) as rt:
        run_operated(rt, switch_and_stop(rt, 2.5 * STATUS_PERIOD,
                                         fault=segment.drives[1].trip_fault, settle=0.5))
    recorded = [(t, m) for topic, t, m in read_messages(str(tmp_path / "rec" / "trace.mcap"))
                if topic == "/rocoma/status"]
    assert len(recorded) >= 2, recorded  # the run lasted 2.5 periods and more
    assert len({t for t, _ in recorded}) == len(recorded)  # each once
    for _, report in recorded:
        assert {"cycle", "buses", "drives"} <= set(report)
        assert [d["name"] for d in report["drives"]] == ["joint1", "joint2"]
        assert report["cycle"]["cycles"] > 0
    first = sorted((tmp_path / "flight").iterdir())[0]  # the fault's
    messages = list(read_messages(str(first)))
    cycles = [t for topic, t, _ in messages if topic == "/rocoma/cycle"]
    kept = [t for topic, t, _ in messages if topic == "/rocoma/status"]
    assert kept and all(cycles[0] - 1e9 * STATUS_PERIOD <= t <= cycles[-1] + 1e9 * STATUS_PERIOD
                        for t in kept)


def test_a_recovery_the_stop_cuts_short_is_told_in_the_recording(demo_bench, bus_factory,
                                                                   tmp_path):
    """A recovery asked over SDO (0x2113) that cannot end (a drive fell silent) and is
    still running when the run stops: the recording says it started and that the stop
    ended it, not that drives failed to come back."""
    from rocoma_can.node.client import ManagerClient
    from rocoma_can.node.objects import RECOVER
    config, segment = demo_bench
    with Runtime(config, record=str(tmp_path)) as rt:
        def operate() -> None:
            wait_for(lambda: rt.manager.switch_blocked() is None, "drives ready", DEMO_WAIT)
            segment.drives[2].set_silent()
            wait_for(lambda: rt.hardware.supervisor.latched[1] is not None,
                     "the silent drive's fault", DEMO_WAIT)
            with ManagerClient(bus_factory(), config.manager.node_id, timeout=DEMO_WAIT) \
                    as client:
                client.write(RECOVER, 1)
            time.sleep(0.2)  # under way, and it cannot end: the drive stays silent
            rt.loop.stop("test")
        run_operated(rt, operate)
    told = [m["cause"] for topic, _, m in read_messages(str(tmp_path / "trace.mcap"))
            if topic == "/rocoma/event" and m["kind"] == "recovery"]
    assert told == ["started", "failed: the run stopped before it ended"], told


def test_a_normal_stop_dumps_nothing(config, tmp_path):
    with Runtime(config, flight=str(tmp_path / "flight"), flight_seconds=1.0) as rt:
        rt.run(duration=0.5, signals=False)
    assert not (tmp_path / "flight").exists() or not list((tmp_path / "flight").iterdir())


def strict_json_messages(path) -> int:
    """Every message of an MCAP file parsed as strict JSON (NaN and Infinity are not JSON:
    Foxglove and PlotJuggler refuse them); their count."""
    from mcap.reader import make_reader

    def refuse(token: str) -> None:
        raise AssertionError(f"{path}: {token} is not JSON")
    count = 0
    with open(path, "rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages():
            assert channel.message_encoding == "json"
            json.loads(message.data, parse_constant=refuse)
            count += 1
    return count


def test_record_writes_every_cycle_and_every_frame_and_exports_csv(config, tmp_path, capsys):
    out = tmp_path / "rec"
    with Runtime(config, record=str(out)) as rt:
        rt.run(duration=1.0, signals=False)
        cycles = rt.loop.stats.cycles
    assert rt.recording is not None and not rt.recording.errors
    trace = [m for topic, _, m in read_messages(str(out / "trace.mcap"))
             if topic == "/rocoma/cycle"]
    assert len(trace) == cycles  # every cycle, the loop's own stop cycles aside
    assert trace[0]["period"] is None and trace[1]["period"] > 0  # no period before the first
    assert strict_json_messages(out / "trace.mcap") > cycles  # Foxglove's parser: no NaN
    events = [m for topic, _, m in read_messages(str(out / "trace.mcap"))
              if topic == "/rocoma/event"]
    assert [e["cause"] for e in events if e["kind"] == "emergency_stop"] \
        == ["loop stopping: duration reached"], events
    (log,) = out.glob("*.log")  # the bus, by name
    frames = list(can.LogReader(str(log)))
    assert any(f.arbitration_id == 0x080 for f in frames)  # the loop's SYNCs
    assert any(f.is_rx for f in frames) and any(not f.is_rx for f in frames)
    # the trace holds the same frames, on /can/<bus> as a flight record has them
    (label,) = [bus.label for bus in config.buses]
    traced = [(t, m) for topic, t, m in read_messages(str(out / "trace.mcap"))
              if topic == f"/can/{label}"]
    assert sorted((f.arbitration_id, bytes(f.data).hex(), not f.is_rx) for f in frames) == \
        sorted((m["id"], m["data"], m["sent"]) for _, m in traced)
    stamps = np.array(sorted(t / 1e9 for t, _ in traced))  # the log's to the µs
    assert np.abs(stamps - sorted(f.timestamp for f in frames)).max() < 1.5e-6
    assert main(["export", str(out / "trace.mcap"), "--csv", str(tmp_path / "t.csv")]) == 0
    with open(tmp_path / "t.csv") as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == cycles and "position[joint2]" in rows[0]  # the joints by name


def test_a_cycle_that_works_past_its_period_is_an_overrun_everywhere(config, tmp_path):
    """Five cycles that start on time and work 1.5 periods: each ends after the next
    cycle's deadline, so each is an overrun, for the loop's statistics and in the
    recording's /rocoma/manager alike (one rule, rocoma_can/overrun.py); asleep, they were
    off the CPU: overruns that waited, each row's ``cpu`` a small part of its ``work``. The
    loop starts the next cycle at once (no burst), so that one is not late by its new
    deadline: a count of late starts alone saw none of them. The run ends a few cycles
    after the fifth (a loaded machine loses cycle slots: a run of a fixed length had only
    four), within a bound of ten times that."""
    out = tmp_path / "rec"
    slow: list[float] = []
    with Runtime(config, record=str(out)) as rt:
        period = rt.loop.period

        def on_cycle(now: float) -> None:
            cycles = rt.loop.stats.cycles
            if len(slow) < 5 and cycles % 10 == 9:
                slow.append(now)
                time.sleep(1.5 * period)
            elif len(slow) == 5 and cycles % 10 == 5:  # the fifth's row and more are in
                rt.loop.stop("five slow cycles done")
        rt.loop.on_cycle = on_cycle
        rt.run(duration=600 * period, signals=False)
        overruns = rt.loop.stats.overruns
    assert len(slow) == 5
    assert overruns >= 5
    messages = list(read_messages(str(out / "trace.mcap")))
    shown = [m for topic, _, m in messages if topic == "/rocoma/manager"]
    assert 5 <= shown[-1]["overruns"] <= overruns  # (sampled: a later overrun may follow)
    # the sleeps were off the CPU: those overruns waited, and the rows say why
    assert 5 <= shown[-1]["overruns_waiting"] <= shown[-1]["overruns"]
    rows = {m["t"]: m for topic, _, m in messages if topic == "/rocoma/cycle"}
    for t in slow:
        assert rows[t]["work"] >= 1.5 * period > 3 * rows[t]["cpu"] > 0, rows[t]


def test_an_unwritable_flight_directory_is_said_and_the_loop_runs_on(config, tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    with Runtime(config, flight=str(blocked / "flight"), flight_seconds=1.0) as rt:
        rt.manager.emergency_stop("test")
        summary = rt.run(duration=1.0, signals=False)
        assert rt.flight is not None
        deadline = time.monotonic() + 5.0
        while len(rt.flight.errors) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        # said at start (the directory tried), then the e-stop's record that failed
        assert len(rt.flight.errors) == 2, rt.flight.errors
        assert rt.flight.errors[0].startswith(f"{blocked / 'flight'}: cannot write flight "
                                              "records: [Errno 20] Not a directory")
        assert rt.flight.errors[1].startswith("flight record ")
    assert summary.cycles >= 0.5 * RATE  # the loop ran its second


def test_plot_draws_state_band_positions_torques_period_and_each_estop(demo_bench, tmp_path,
                                                                       capsys):
    """The figure's axes, not its pixels: the five panels, a position and a target line per
    joint, the controllers on the band, a line at the e-stop with its cause listed."""
    from rocoma_can.record.plot import PANELS, figure, load_trace
    config, segment = demo_bench
    out = tmp_path / "rec"
    with Runtime(config, record=str(out)) as rt:
        run_operated(rt, switch_and_stop(rt, 1.0, fault=segment.drives[1].trip_fault,
                                         settle=0.5))
    trace = load_trace(out / "trace.mcap")
    causes = [cause for _, cause in trace.estops]
    assert len(causes) == 2 and "(node 1)" in causes[0] and causes[1] == "loop stopping: test"
    fig = figure(trace)
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    assert [next(t for t in titles if t.startswith(p)) for p in PANELS]  # each panel once
    band, position, torque, period, jitter = fig.axes
    assert len(position.get_lines()) == 2 * 2 + len(causes)  # measured + target per joint
    assert len(torque.get_lines()) == 2 * 2 + len(causes)
    estop_x = [line.get_xdata()[0] for line in band.get_lines()]
    assert estop_x == pytest.approx([t for t, _ in trace.estops])
    assert {"pd", "damp"} <= {text.get_text() for text in band.texts}
    assert causes[0] in fig.get_supxlabel()
    assert jitter.patches  # the histogram's bars
    targets = position.get_lines()[1].get_ydata()
    assert np.isfinite(targets).any()  # commanded in CSP while pd ran
    assert main(["plot", str(out / "trace.mcap"), "--out", str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"plot written to {tmp_path / 'p.png'}" in capsys.readouterr().out
    assert main(["plot", str(out / "trace.mcap"), "--out", str(tmp_path / "p.txt")]) == 2
    assert "p.txt: cannot write the plot" in capsys.readouterr().err


@contextmanager
def tmpfs(mount: Path, options: str = "") -> Iterator[Path]:
    """A 64 KiB tmpfs of our own at ``mount`` (root mounts it), unmounted afterwards; the
    test is skipped, saying so, where mounting is not permitted."""
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size=64k{options}", "tmpfs",
                           str(mount)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"NOT TESTED: a full or read-only disk needs `mount -t tmpfs` (root, "
                    f"CAP_SYS_ADMIN): {done.stderr.strip() or done.returncode}")
    try:
        yield mount
    finally:
        if subprocess.run(["umount", str(mount)]).returncode != 0:
            subprocess.run(["umount", "-l", str(mount)])  # a file left open: a failure
            pytest.fail(f"{mount} was still in use: a writer left its file open")


def fill(mount: Path, leave: int = 0) -> None:
    """Write into ``mount`` until at most ``leave`` bytes are free."""
    with open(mount / "filler", "wb") as stream:
        try:
            while os.statvfs(mount).f_bavail * os.statvfs(mount).f_frsize > leave:
                stream.write(b"\0" * 4096)
                stream.flush()
        except OSError:
            pass


@pytest.fixture(params=["full", "read-only"])
def small_disk(request, tmp_path) -> Iterator[tuple[str, Path]]:
    """(kind, a directory on a 64 KiB tmpfs): filled to the brim, or mounted read-only."""
    with tmpfs(tmp_path / "disk", ",ro" if request.param == "read-only" else "") as mount:
        if request.param == "full":
            fill(mount)
        yield request.param, mount


def open_files_under(directory: Path) -> list[str]:
    """The files this process holds open under ``directory``."""
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(f"{directory}/"):
            found.append(target)
    return found


def writer_threads() -> list[str]:
    """The recorder's threads and writer processes still there (none once a run ended)."""
    threads = [t.name for t in threading.enumerate()
               if t.name.startswith(("can-log", "recorder-"))]
    children = subprocess.run(["pgrep", "-f", "-P", str(os.getpid()),
                               "rocoma_can.record.writer"], capture_output=True, text=True)
    return threads + children.stdout.split()


def test_run_record_on_a_disk_that_fills_up(demo_bench, tmp_path, capfd, caplog):
    """A file fills the disk during the run (a candump log, or trace.mcap as its chunks of
    frames go out): every writer stops and closes its file at once, one warning naming the
    file that failed, the loop runs its time; run says it stopped as usual and exits 1 (the
    recording has a hole)."""
    config, _segment = demo_bench
    path = tmp_path / "robot.yaml"
    cfg = demo_config(config.bus.channel, drives=2, rate=RATE)
    cfg["manager"]["estop_must_be_cleared"] = False
    path.write_text(yaml.safe_dump(cfg))
    caplog.set_level("WARNING")
    with tmpfs(tmp_path / "disk") as mount:
        fill(mount, leave=8192)
        record = mount / "rec"
        assert main(["run", str(path), "--record", str(record), "--no-flight",
                     "--duration", "2"]) == 1
        out, err = capfd.readouterr()
        assert "rocoma-can: stopped (duration reached)" in out and "Traceback" not in err
        said = [r for r in caplog.records if r.levelno >= logging.WARNING]
        assert [(r.levelname, r.exc_info) for r in said] == [("WARNING", None)], \
            [r.getMessage() for r in said]
        message = said[0].getMessage()
        assert re.fullmatch(rf"recording to {re.escape(str(record))} stopped, the loop runs "
                            rf"on: {re.escape(str(record))}/(?:\S+\.log: writing failed after "
                            r"\d+ frames|trace\.mcap: writing failed): \[Errno 28\] No space "
                            r"left on device", message), message
        assert open_files_under(mount) == [] and writer_threads() == []


def test_a_recording_that_cannot_be_written_stops_every_writer(config, small_disk, caplog):
    """On a full disk the run records nothing, says so once and runs its time; on a
    read-only one the Runtime does not start (its files cannot be made). Either way no
    writer thread or open file is left."""
    from rocoma_can.record.can_log import RecordingError
    kind, mount = small_disk
    caplog.set_level("WARNING")
    if kind == "read-only":
        with pytest.raises(RecordingError) as err:
            Runtime(config, record=str(mount))
        log_file = mount / f"{_slug(config.buses[0].label)}.log"  # the first file made
        assert str(err.value) == (f"{log_file}: cannot write: [Errno 30] Read-only file "
                                  f"system: '{log_file}'")
    else:
        record = mount / "rec"
        with Runtime(config, record=str(record)) as rt:
            summary = rt.run(duration=1.0, signals=False)
        assert rt.recording is not None and rt.recording.errors
        assert "[Errno 28] No space left on device" in rt.recording.errors[0]
        assert summary.cycles >= 0.5 * RATE  # the loop ran its second
        assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] \
            == [f"recording to {record} stopped, the loop runs on: {rt.recording.errors[0]}"]
    assert open_files_under(mount) == [] and writer_threads() == []


def test_the_flight_recorder_leaves_no_file_where_it_cannot_write(config, small_disk):
    kind, mount = small_disk
    flight = mount / "flight" if kind == "full" else mount
    with Runtime(config, flight=str(flight), flight_seconds=1.0) as rt:
        rt.manager.emergency_stop("test")
        summary = rt.run(duration=1.0, signals=False)
        assert rt.flight is not None
        deadline = time.monotonic() + DEMO_WAIT
        while not any(e.startswith("flight record ") for e in rt.flight.errors) \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        errors = list(rt.flight.errors)
    said = (r"\[Errno 28\] No space left on device" if kind == "full"
            else r"\[Errno 30\] Read-only file system")
    if kind != "full":  # (a full disk still takes an empty file: found at the record)
        assert errors[0] == (f"{flight}: cannot write flight records: [Errno 30] Read-only "
                             "file system (each e-stop's is tried, and said if it fails)")
        errors = errors[1:]
    assert errors and re.fullmatch(rf"flight record {re.escape(str(flight))}/flight-\S+"
                                   rf"-test\.mcap: {said}", errors[0]), errors
    assert summary.cycles >= 0.5 * RATE  # the loop ran its second
    left = sorted(p.name for p in mount.rglob("*"))
    assert left == (["filler", "flight"] if kind == "full" else []), left  # no flight-*.mcap
    assert open_files_under(mount) == [] and writer_threads() == []


def test_a_frame_log_that_failed_keeps_nothing_more(tmp_path):
    """After a failed write no frame is queued any more: nothing would write it, and the
    bus reader goes on handing frames to it for the rest of the run."""
    from rocoma_can.record.can_log import FrameLog
    with tmpfs(tmp_path / "disk") as mount:
        fill(mount)
        frame_log = FrameLog(mount / "bus.log", flush_period=0.01).start()
        msg = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
        deadline = time.monotonic() + DEMO_WAIT
        while frame_log.error is None and time.monotonic() < deadline:
            for _ in range(500):
                frame_log.on_message_received(msg)
            time.sleep(0.02)
        assert frame_log.error is not None and frame_log.error.endswith(
            "[Errno 28] No space left on device"), frame_log.error
        frame_log.on_message_received(msg)
        assert len(frame_log._queue) == 0
        frame_log.stop()
        assert open_files_under(mount) == [] and writer_threads() == []


def test_a_directory_holding_an_earlier_recording_is_not_written_over(tmp_path, capfd):
    """`run --record DIR` again from the shell's history wrote over the last run's
    trace.mcap and bus logs without a word: the record of what went wrong, lost. The run
    is refused before it starts (exit 2), naming what DIR holds; the files stay as they
    were."""
    from fixtures.configs import nobody_answers
    config = nobody_answers(tmp_path)
    record = tmp_path / "rec"
    record.mkdir()
    earlier = {"trace.mcap": b"an earlier run's trace", "notes.txt": b"the operator's"}
    for name, data in earlier.items():
        (record / name).write_bytes(data)
    assert main(["run", str(config), "--record", str(record), "--no-flight",
                 "--duration", "0.2"]) == 2
    _, err = capfd.readouterr()
    assert f"{record}: holds an earlier recording (trace.mcap): not written over; " \
           "give --record a new directory, or move them" in err, err
    assert {p.name: p.read_bytes() for p in record.iterdir()} == earlier


def test_the_demo_refuses_a_directory_holding_an_earlier_recording_in_one_line(tmp_path,
                                                                                capfd):
    """The demo's --record the same (RecordingError came through as a traceback)."""
    record = tmp_path / "rec"
    record.mkdir()
    (record / "trace.mcap").write_bytes(b"an earlier demo's")
    assert main(["demo", "--drives", "2", "--duration", "0.5", "--record",
                 str(record)]) == 2
    out, err = capfd.readouterr()
    assert "Traceback" not in err and (
        f"demo: --record: {record}: holds an earlier recording (trace.mcap): not written "
        "over; give --record a new directory, or move them") in out.splitlines(), out
    assert (record / "trace.mcap").read_bytes() == b"an earlier demo's"
