"""The demo's simulated drives in a process of their own (rocoma_can/cli/demo/drives.py): they
answer on this process's in-process buses through the link, take the operator's faults,
report their failures, and end with the demo, or are said to have ended when they die."""
from __future__ import annotations

import os
import re
import signal
import uuid

import can
import pytest

from rocoma_can.cli.demo.drives import SimProcess
from rocoma_can.cli.demo.walkthrough import DemoOptions, Walkthrough
from rocoma_can.cli.exit_codes import USAGE
from rocoma_can.cli.main import main
from rocoma_can.errors import SimulatorFailed

WAIT = 10.0  # s: a bound for the child's frames, never expected to be reached


def _open(channel: str) -> can.BusABC:
    return can.Bus(interface="inproc", channel=channel, ignore_config=True)


def _until(bus: can.BusABC, cob_id: int) -> can.Message:
    while True:
        msg = bus.recv(WAIT)
        assert msg is not None, f"no frame 0x{cob_id:03X} from the simulator process"
        if msg.arbitration_id == cob_id:
            return msg


@pytest.fixture
def channels() -> list[str]:
    tag = uuid.uuid4().hex[:8]
    return [f"sim-{tag}-0", f"sim-{tag}-1"]


def test_the_childs_drives_answer_on_this_process_buses_and_take_faults(channels):
    buses = [_open(c) for c in channels]  # listening before the drives power on
    sim = SimProcess([(channels[0], [1, 2]), (channels[1], [3])], None, 3, False)
    try:
        assert sim._child.pid != os.getpid() and sim._child.poll() is None
        assert sim.node_ids == [1, 2]
        # each drive boots on its own bus: boot-up (0x700 + node, state 0)
        for bus, nodes in ((buses[0], (1, 2)), (buses[1], (3,))):
            for node in nodes:
                assert bytes(_until(bus, 0x700 + node).data) == b"\x00"
        # an SDO upload of 0x1000 (device type) from node 3, answered by the child
        buses[1].send(can.Message(arbitration_id=0x603, is_extended_id=False,
                                  data=b"\x40\x00\x10\x00\x00\x00\x00\x00"))
        answer = _until(buses[1], 0x583)
        assert answer.data[0] & 0xE0 == 0x40 and bytes(answer.data[1:4]) == b"\x00\x10\x00"
        assert int.from_bytes(answer.data[4:6], "little") == 402  # a CiA 402 drive
        tripped = sim.trip_fault(2)
        emcy = _until(buses[0], 0x82)
        assert int.from_bytes(emcy.data[0:2], "little") == 0x1000
        assert tripped > 0
        sim.check()
    finally:
        sim.stop()
        for bus in buses:
            bus.shutdown()
    assert sim._child.returncode == 0  # it ended on stop, not killed
    assert sim.link.closed.is_set()


def test_a_simulator_process_that_dies_is_said_and_nothing_waits_for_it(channels):
    sim = SimProcess([(channels[0], [1])], None, 1, False)
    try:
        os.kill(sim._child.pid, signal.SIGKILL)
        sim._child.wait(WAIT)
        assert sim.link.closed.wait(WAIT)  # its end of the link closed with it
        with pytest.raises(RuntimeError, match=r"simulator process ended \(exit code -9\)"):
            sim.check()
        with pytest.raises(RuntimeError, match="simulator process ended"):
            sim.trip_fault(1)
    finally:
        sim.stop()


def test_a_failed_request_says_what_failed(channels):
    sim = SimProcess([(channels[0], [1])], None, 1, False)
    try:
        with pytest.raises(RuntimeError, match=r"trip_fault failed: KeyError: 9"):
            sim.trip_fault(9)  # no drive 9
        sim.check()  # and the child serves on
    finally:
        sim.stop()


def test_the_demo_passes_with_its_drives_in_a_process_of_their_own_or_in_the_loops():
    """Both ways pass the walk-through, and the demo says where the drives run."""
    for sim, where in (("process", r"in a process of their own \(pid (\d+)\)"),
                       ("loop", "in this process, stepped by the loop")):
        seen: list[str] = []
        report = Walkthrough(DemoOptions(drives=3, rate=200.0, duration=3.0, sim=sim),
                             out=seen.append).run()
        assert report.ok, "\n".join(seen)
        said = [m for m in map(re.compile(f"rocoma-can demo: the simulated drives run {where}")
                                .match, seen) if m]
        assert len(said) == 1, "\n".join(seen)
        if sim == "process":
            assert int(said[0].group(1)) != os.getpid()


def test_a_process_on_a_bus_no_link_joins_is_refused(capsys):
    assert main(["demo", "--sim", "process", "--interface", "virtual"]) == USAGE
    assert "demo: --sim process needs --interface inproc: the virtual bus joins no other " \
        "process" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--sim process needs --interface inproc"):
        Walkthrough(DemoOptions(drives=2, sim="process", interface="virtual"),
                    out=lambda line: None).run()
    with pytest.raises(ValueError, match="--sim must be one of loop, process, got 'thread'"):
        Walkthrough(DemoOptions(drives=2, sim="thread"), out=lambda line: None).run()


def test_a_demo_whose_drives_process_dies_fails_and_says_so(monkeypatch):
    """The drives' process killed mid-run: the operator's next fault injection fails, the
    walk-through ends, the loop's stop still sends every drive its torque-off frames, and
    the demo fails, saying why (the drives' silence is for the manager's supervision to
    see: test_driver_bus_supervision)."""
    started: list[SimProcess] = []
    real_init = SimProcess.__init__

    def keep(self: SimProcess, *args: object, **kwargs: object) -> None:
        real_init(self, *args, **kwargs)  # type: ignore[arg-type]
        started.append(self)
    monkeypatch.setattr(SimProcess, "__init__", keep)
    seen: list[str] = []

    def out(line: str) -> None:
        seen.append(line)
        if line.startswith("ok  switch to pd") and started:
            os.kill(started[0]._child.pid, signal.SIGKILL)
    report = Walkthrough(DemoOptions(drives=3, rate=200.0, duration=3.0, sim="process"),
                         out=out).run()
    assert not report.ok
    text = "\n".join(seen)
    assert "FAILED simulated drives: simulator process ended (exit code -9)" in text, text
    assert "FAILED operator: SimulatorFailed: simulator process ended (exit code -9)" in text
    stop = next(s for s in report.steps if s.name == "loop stop -> torque-off frames")
    assert stop.ok, stop.detail


def test_a_simulator_process_that_ends_early_fails_the_check_whatever_its_code(channels):
    """Ended before the demo stopped it, with exit code 0 too (its link gone, say): the
    drives were gone, so the check says so."""
    sim = SimProcess([(channels[0], [1])], None, 1, False)
    try:
        sim.link.close()  # the child's link ends: it ends, by itself, with code 0
        sim._child.wait(WAIT)
        assert sim._child.returncode == 0
        with pytest.raises(SimulatorFailed, match=r"simulator process ended \(exit code 0\)"):
            sim.check()
    finally:
        sim.stop()


def test_a_late_answer_is_not_taken_for_the_next_requests(channels):
    sim = SimProcess([(channels[0], [1])], None, 1, False)
    try:
        sim._replies.put({"ok": True, "id": 99})  # as if a request timed out before it came
        assert sim.trip_fault(1) > 0  # its own answer, with "tripped"
        sim.check()
    finally:
        sim.stop()
