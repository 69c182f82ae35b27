"""Recording off the loop's interpreter (record/rings.py, recorder.py, writer.py): the loop's
process only copies into shared memory, a writer process writes; what it writes holds every
cycle and every frame; the loop's part allocates nothing; a writer that dies, or a manager
process that dies, loses the run nothing it could keep."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections import defaultdict

import can
from fixtures.paths import TESTS
from fixtures.running import (
    BENCH_RATE,
    DEMO_RUN,
    DEMO_WAIT,
    run_operated,
    switch_and_stop,
    wait_for,
)

from rocoma_can import ManagerState
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.record.rings import FrameRing, RingReader, SharedFile, frame_fields, layout
from rocoma_can.record.trace import RowLayout, SignalTrace, read_messages
from rocoma_can.runtime import Runtime


def test_the_recording_holds_every_frame_an_independent_listener_saw(demo_bench, tmp_path,
                                                                     bus_factory):
    """Every frame on the bus, received by the hardware or sent by it, is in the bus's
    candump file, in order per COB-ID, with what the manager sent marked T (its own reader
    never sees those: they come from BusPort) and what it received R. An independent
    listener on the bus is the reference; only frames in flight at the ends may differ."""
    config, _segment = demo_bench
    listener = bus_factory(receive_own_messages=False)
    heard: list[can.Message] = []
    reading = threading.Event()

    def listen() -> None:
        while not reading.is_set():
            msg = listener.recv(0.05)
            if msg is not None:
                heard.append(msg)
    thread = threading.Thread(target=listen)
    thread.start()
    try:
        with Runtime(config, record=str(tmp_path / "rec")) as rt:
            run_operated(rt, switch_and_stop(rt, 1.0))
            cycles = rt.loop.stats.cycles
    finally:
        time.sleep(0.1)
        reading.set()
        thread.join(5.0)
    assert rt.recording is not None and not rt.recording.errors, rt.recording.errors
    [log_file] = (tmp_path / "rec").glob("*.log")
    recorded = list(can.LogReader(str(log_file)))
    stamps = [msg.timestamp for msg in recorded]
    assert stamps == sorted(stamps)  # canplayer replays in file order
    by_id: dict[int, list[bytes]] = defaultdict(list)
    for msg in heard:
        by_id[msg.arbitration_id].append(bytes(msg.data))
    ours: dict[int, list[bytes]] = defaultdict(list)
    for msg in recorded:
        ours[msg.arbitration_id].append(bytes(msg.data))
    sent = {0x080, 0x201, 0x202, 0x700 + config.manager.node_id}  # SYNC, RPDOs, heartbeat
    received = {0x181, 0x182, 0x701, 0x702}                       # TPDOs, drive heartbeats
    for cob_id in sent | received:
        assert ours[cob_id], f"no 0x{cob_id:03X} recorded"
        theirs = by_id[cob_id]
        # the recording is one stretch of what the listener heard (the drives' heartbeats
        # began before the manager did) ...
        assert any(theirs[k:k + len(ours[cob_id])] == ours[cob_id]
                   for k in range(len(theirs) - len(ours[cob_id]) + 1)), hex(cob_id)
        # ... and of what the cycle made happen, all but what was on its way at the end
        if cob_id not in (0x701, 0x702):
            assert len(theirs) - len(ours[cob_id]) <= 2, hex(cob_id)
    for msg in recorded:
        if msg.arbitration_id in sent:
            assert not msg.is_rx, msg
        elif msg.arbitration_id in received:
            assert msg.is_rx, msg
    syncs = len(ours[0x080])
    assert syncs >= cycles  # a SYNC every cycle (and the loop's stop cycles')
    trace = [m for topic, _, m in read_messages(str(tmp_path / "rec" / "trace.mcap"))
             if topic == "/rocoma/cycle"]
    assert len(trace) == cycles


def test_the_flight_record_has_the_frames_the_hardware_read_and_sent(demo_bench, tmp_path):
    """No second bus handle: the hardware's own reader and sends feed the flight recorder.
    The record has both directions, each frame marked."""
    config, segment = demo_bench
    from rocoma_can.drivers.link.bus_port import BusPort
    opened: list[object] = []
    original = BusPort.open

    def counting_open(self, cob_ids):  # every bus handle the runtime opens for drives
        opened.append(self)
        return original(self, cob_ids)
    BusPort.open = counting_open  # type: ignore[method-assign]
    try:
        with Runtime(config, flight=str(tmp_path / "flight"), flight_seconds=1.0) as rt:
            run_operated(rt, switch_and_stop(rt, 0.5, fault=segment.drives[1].trip_fault))
    finally:
        BusPort.open = original  # type: ignore[method-assign]
    assert len(opened) == 1
    first = sorted((tmp_path / "flight").iterdir())[0]
    frames = [m for topic, _, m in read_messages(str(first)) if topic.startswith("/can/")]
    assert {m["id"] for m in frames if m["sent"]} >= {0x080, 0x201, 0x202}
    assert {m["id"] for m in frames if not m["sent"]} >= {0x181, 0x182}


def test_the_loops_part_allocates_nothing(tmp_path):
    """A cycle's row and a frame into the shared rings: no memory block left behind, over
    thousands of calls (the loop's thread must not feed the garbage collector)."""
    state, command = JointState.zeros(12), JointCommand.zeros(12)
    rows, frames = layout([("rows", 500, RowLayout(state.names).width, False),
                           ("bus sent", 500, 0, False)])
    shared = SharedFile(frames.offset + frames.size)

    class Manager:
        active_controller_name = "pd"
    trace = SignalTrace(state, command, Manager(), rows.capacity, rows=shared.array(rows),
                        publish=lambda n: shared.publish(rows, n), known=["pd"])
    ring = FrameRing(shared, frames, sent=True)
    msg = can.Message(arbitration_id=0x201, data=bytearray(8), is_extended_id=False)
    stamp = time.time()
    for k in range(1000):  # warm: caches, the first allocation of everything
        trace.record(k * 1e-3, 1e-4, 0.0, ManagerState.OK, 1e-4)
        ring.put(msg, stamp)
    before = sys.getallocatedblocks()
    for k in range(5000):
        trace.record(k * 1e-3, 1e-4, 0.0, ManagerState.OK, 1e-4)
        ring.put(msg, stamp)
    assert sys.getallocatedblocks() - before < 10
    assert shared.count(rows) == 6000 and shared.count(frames) == 6000
    start, records = RingReader(shared, frames).read(0)
    assert start == 5501 and len(records) == 499  # the ring's last 499 (its next slot: not)
    assert frame_fields(records[:1]) == [(stamp, 0x201, 64, "0000000000000000")]


def test_a_writer_process_that_dies_is_said_and_the_loop_runs_on(demo_bench, tmp_path, caplog):
    config, _segment = demo_bench
    caplog.set_level("WARNING")
    with Runtime(config, record=str(tmp_path / "rec"), flight=str(tmp_path / "flight")) as rt:
        assert rt.recorder is not None
        writer = rt.recorder._process
        def kill() -> None:
            wait_for(lambda: rt.loop.stats.cycles > 20, "cycles", DEMO_WAIT)
            writer.kill()
            wait_for(lambda: rt.recording is not None and rt.recording.errors,
                     "the writer's death said", DEMO_WAIT)
            time.sleep(0.3)
            rt.loop.stop("test")
        worker = threading.Thread(target=kill)
        worker.start()
        summary = rt.run(duration=DEMO_RUN, signals=False)
        worker.join(DEMO_WAIT)
    assert rt.loop.stop_reason == "test"
    assert summary.cycles >= 40  # it ran on after the writer died
    assert rt.recording.errors[0].startswith("the recording's writer process ended")
    assert rt.flight is not None and rt.flight.errors
    assert writer.poll() is not None


def _kill_a_manager_process(demo_bench, tmp_path, record: bool) -> None:
    """Run a manager in a process of its own for a second and SIGKILL it; wait for its
    writer to end."""
    config, _segment = demo_bench
    channel = config.bus.channel
    recording = f", record={str(tmp_path / 'rec')!r}" if record else ""
    script = textwrap.dedent(f"""
        import sys, time, threading
        sys.path.insert(0, {str(str(TESTS))!r})
        from rocoma_can.cli.demo.config import demo_config
        from rocoma_can.runtime import Runtime
        from rocoma_can.runtime.config import validate
        from fixtures.sim import SimulatedSegment
        seg = SimulatedSegment.open({channel!r} + "-child", "virtual", [1, 2])
        cfg = demo_config({channel!r} + "-child", drives=2, rate={BENCH_RATE})
        rt = Runtime(validate(cfg), flight={str(tmp_path / "flight")!r}, flight_seconds=1.0
                     {recording})
        print(rt.recorder._process.pid, flush=True)
        rt.run(duration=60, signals=False)
    """)
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        writer = int(child.stdout.readline())
        time.sleep(1.5)  # a second of cycles in the rings
        child.send_signal(signal.SIGKILL)
        child.wait(DEMO_WAIT)
        wait_for(lambda: not os.path.exists(f"/proc/{writer}") or
                 open(f"/proc/{writer}/stat").read().split()[2] == "Z",
                 "the writer ends", DEMO_WAIT)
    finally:
        if child.poll() is None:
            child.kill()


def test_a_killed_manager_process_still_leaves_a_flight_record(demo_bench, tmp_path):
    """The writer outlives the manager's process by the time it takes to write what the
    rings hold: SIGKILL the process running the loop, and the flight record of its last
    seconds is there, and the writer has ended."""
    _kill_a_manager_process(demo_bench, tmp_path, record=False)
    [record] = list((tmp_path / "flight").iterdir())
    assert "process-ended-without-closing" in record.name
    cycles = [m for topic, _, m in read_messages(str(record)) if topic == "/rocoma/cycle"]
    assert len(cycles) >= 0.5 * BENCH_RATE


def test_a_killed_manager_process_leaves_its_recording_whole(demo_bench, tmp_path):
    """With --record too: the recording is closed whole (its MCAP summary written) after
    the flight record, although nobody reads the writer's answers any more (the writer
    died of the broken pipe before it closed the recording)."""
    _kill_a_manager_process(demo_bench, tmp_path, record=True)
    [record] = list((tmp_path / "flight").iterdir())
    assert "process-ended-without-closing" in record.name
    cycles = [m for topic, _, m in read_messages(str(tmp_path / "rec" / "trace.mcap"))
              if topic == "/rocoma/cycle"]
    assert len(cycles) >= 0.5 * BENCH_RATE


def test_a_recording_carries_the_live_views_channels_the_layout_reads(demo_bench, tmp_path):
    """A recording and a flight record open in Foxglove with the live view's layout: every
    topic the shipped layout reads (the status report aside: the writer never sees it) is
    in both, with the schema the live view serves, and /tf moves with the joints."""
    from fixtures.foxglove_layout import layout_topics

    from rocoma_can.cli.demo.config import demo_urdf
    from rocoma_can.live import messages
    from rocoma_can.live.urdf import parse_urdf
    config, segment = demo_bench
    config.robot = parse_urdf(demo_urdf([d.name for d in config.drives]).encode(), "demo")
    with Runtime(config, record=str(tmp_path / "rec"), flight=str(tmp_path / "flight"),
                 flight_seconds=1.0) as rt:
        run_operated(rt, switch_and_stop(rt, 1.0, "trajectory",  # trajectory: it moves
                                         segment.drives[1].trip_fault))
    wanted = layout_topics() - {messages.STATUS.topic}
    flight = sorted((tmp_path / "flight").iterdir())[0]
    for path in (tmp_path / "rec" / "trace.mcap", flight):
        got: dict[str, list[dict]] = defaultdict(list)
        for topic, _, message in read_messages(str(path)):
            got[topic].append(message)
        assert wanted <= set(got), (path, wanted - set(got))
        assert len(got["/robot_description"]) == 1
        assert got["/robot_description"][0]["data"] == config.robot.text
        names = got["/joint_states"][-1]["name"]
        assert names == [d.name for d in config.drives]
        assert len(got["/joint_states"]) == len(got["/rocoma/cycle"])
        angles = {json_rotation(t) for m in got["/tf"] for t in m["transforms"]
                  if t["child_frame_id"] == "joint1_link"}
        assert len(angles) > 3, angles  # the arm moved
        assert any("e-stop" in m["message"] for m in got["/rocoma/log"])
        assert got["/rocoma/manager"][-1]["state"] in ("EMERGENCY", "FAILPROOF")


def json_rotation(transform: dict) -> tuple[float, ...]:
    return tuple(round(transform["rotation"][k], 4) for k in "xyzw")


def test_a_stop_signal_to_every_process_of_the_service_leaves_the_writer_to_its_close(
        demo_bench, tmp_path):
    """systemd stops a service by sending SIGTERM to every process of it (its cgroup), the
    writer too: the loop's process stops on it, torque-off first, and closes the writer,
    which must still be there to write the run's end (it died at once: a recording cut
    short, no record of a shutdown after an e-stop)."""
    config, _segment = demo_bench
    with Runtime(config, record=str(tmp_path / "rec")) as rt:
        assert rt.recorder is not None
        writer = rt.recorder._process

        def stop() -> None:
            wait_for(lambda: rt.loop.stats.cycles > 20, "cycles", DEMO_WAIT)
            writer.send_signal(signal.SIGTERM)
            rt.loop.on_signal(signal.SIGTERM, None)  # the loop's process got its own
        worker = threading.Thread(target=stop)
        worker.start()
        rt.run(duration=DEMO_RUN, signals=False)
        worker.join(DEMO_WAIT)
    assert rt.loop.stop_reason == "signal SIGTERM"
    assert rt.recording is not None and not rt.recording.errors, rt.recording.errors
    cycles = [m for topic, _, m in read_messages(str(tmp_path / "rec" / "trace.mcap"))
              if topic == "/rocoma/cycle"]
    assert len(cycles) == rt.loop.stats.cycles


def test_the_writer_keeps_off_the_cpus_the_loop_is_pinned_to(demo_bench, tmp_path):
    """realtime.cpus pins the loop's thread; the writer process runs on the other CPUs,
    every thread of it, even when it was started from a thread pinned whole to the loop's
    CPU (it inherits that); with no other CPU it stays where it is."""
    config, _segment = demo_bench
    allowed = os.sched_getaffinity(0)
    config.cpus = {min(allowed)}
    os.sched_setaffinity(0, config.cpus)  # this thread: the process pinned whole
    try:
        with Runtime(config, flight=str(tmp_path / "flight")) as rt:
            assert rt.recorder is not None
            writer = rt.recorder._process.pid
            tasks = os.listdir(f"/proc/{writer}/task")  # (numpy's threads among them)
            expected = allowed - config.cpus or config.cpus
            assert {t: os.sched_getaffinity(int(t)) for t in tasks} == \
                {t: expected for t in tasks}
    finally:
        os.sched_setaffinity(0, allowed)

