"""The audit trail (rocoma_can/audit.py): every operator request, through every surface
that takes one, is one line saying who (the surface), what and the answer; every change of
the manager's state one line; none of them written on the control loop's thread. ``run``'s
console shows them, with every other line, in one format."""
from __future__ import annotations

import logging
import signal
import threading

import pytest
import yaml
from fixtures.console import untimed
from fixtures.paths import TESTS
from fixtures.running import DEMO_WAIT, runtime_running, wait_for

from rocoma_can import ControllerManager, add_to_manager
from rocoma_can.audit import AUDIT, Audit
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.exit_codes import OK
from rocoma_can.cli.main import main
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.drivers.link.bus import open_bus
from rocoma_can.errors import NoAnswer
from rocoma_can.node.client import ManagerClient
from rocoma_can.node.objects import CLEAR, ESTOP, RECOVER
from rocoma_can.remote import Transport, serve
from rocoma_can.stop_surfaces import FOXGLOVE, ZENOH


def _lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == AUDIT]


def _bench(channel: str) -> dict:
    cfg = demo_config(channel, drives=2, rate=100)
    cfg["bus"]["interface"] = "virtual"
    return cfg


def test_every_sdo_request_is_one_audit_line_written_off_the_loop(
        virtual_channel, sim_segment_factory, caplog):
    sim_segment_factory(2)
    with caplog.at_level(logging.INFO, logger=AUDIT), \
            runtime_running(_bench(virtual_channel), DEMO_WAIT) as rt:
        wait_for(lambda: rt.hardware.all_ready, "bring-up", DEMO_WAIT)
        bus = open_bus("virtual", virtual_channel, receive_own_messages=False)
        try:
            client = ManagerClient(bus, 100, timeout=1.0)
            with pytest.raises(Exception, match="refused"):
                client.switch("pd")                     # latched
            client.write(CLEAR, 1)
            client.write(CLEAR, 1)                      # nothing left to clear
            with pytest.raises(Exception, match="0x06090030|not found|Not found"):
                client.switch("pdd")
            assert client.switch("pd", timeout=DEMO_WAIT) == 0
            wait_for(lambda: rt.hardware.all_enabled, "the drives enabled", DEMO_WAIT)
            assert client.home("joint1", timeout=DEMO_WAIT) == "homed"
            with pytest.raises(Exception, match="refused"):
                client.home("knee")                      # no such drive
            client.write(ESTOP, 1)
            wait_for(lambda: rt.manager.state.name == "EMERGENCY", "the e-stop", DEMO_WAIT)
            client.write(RECOVER, 1)
            wait_for(lambda: any(line.startswith("recovery done") for line in
                                 _lines(caplog)), "the recovery", DEMO_WAIT)
            client.close()
        finally:
            bus.shutdown()
        loop = next(t for t in threading.enumerate() if t.name == "test-loop")
    said = _lines(caplog)
    node = "SDO (node 100)"
    expected = [
        f"{node}: switch to 'pd': refused: emergency stop not cleared",
        f"{node}: clear: the e-stop latch is cleared",
        f"{node}: clear: nothing to clear (the e-stop latch was not set)",
        f"{node}: switch to 'pdd': NOT_FOUND (controllers: pd, trajectory)",
        "state OK, controller pd",
        f"{node}: switch to 'pd': SWITCHED",
        f"{node}: home 'joint1': started",
        f"{node}: home 'joint1': homed",
        f"{node}: home 'knee': refused: no drive named 'knee' (drives: joint1, joint2)",
        "e-stop (EMERGENCY): SDO e-stop (0x2110)",
        f"{node}: recover: started",
        "recovery started (EMERGENCY)",
    ]
    assert [line for line in said if line in expected] == expected, said
    assert said.index(expected[-1]) < next(k for k, line in enumerate(said)
                                           if line.startswith("recovery done"))
    # the audit's records are written by the manager's event thread, the node's reader,
    # the bring-up workers: never by the loop
    assert not [r for r in caplog.records if r.thread == loop.ident], \
        [(r.threadName, r.getMessage()) for r in caplog.records if r.thread == loop.ident]


def test_the_remote_surfaces_requests_are_told_alike(caplog):
    """Zenoh's and Foxglove's requests (remote.serve, their one set of rules): each one
    and its answer, a refusal too, named by the surface."""
    from fixtures.joint_plant import JointPlant
    plant = JointPlant(2, dt=0.01)
    manager = ControllerManager(TorqueOff(), 0.01, plant.state, plant.command, timing=None,
                                estop_must_be_cleared=True)
    add_to_manager(manager, {"controllers": [{"name": "pd", "plugin": "pd"}]})
    manager.subscribe(Audit())
    zenoh = Transport(ZENOH, "zenoh.allow_commands", True)
    foxglove = Transport(FOXGLOVE, "foxglove.allow_commands", False)
    try:
        with caplog.at_level(logging.INFO, logger=AUDIT):
            manager.emergency_stop("test")
            manager.update()
            serve(manager, "clear", zenoh, True, None)
            serve(manager, "recover", zenoh, True, None)
            serve(manager, "clear", foxglove, True, None)
            wait_for(lambda: len(_lines(caplog)) >= 5, "the lines", DEMO_WAIT)
    finally:
        manager.shutdown()
    assert _lines(caplog) == [
        "e-stop (FAILPROOF): test",
        "state FAILPROOF, controller torque_off: emergency stop cleared",  # the latch's change
        "Zenoh: clear: the e-stop latch is cleared",                       # who asked for it
        "Zenoh: recover: refused: this manager has no drives to recover",
        "Foxglove: clear: refused: clear over Foxglove is not allowed by this manager's "
        "config (foxglove.allow_commands: false); e-stop and failproof are"]


def test_run_speaks_in_one_format_and_says_the_operators_actions(virtual_channel,
                                                                 sim_segment_factory,
                                                                 tmp_path, capfd):
    """``rocoma-can run``'s console, whole: its own lines, the audit trail (an operator's
    requests and the manager's changes) and the library's warnings and errors, every line
    with its time, each warning once (a note of the drives' file for both drives: one
    line); the operator's Ctrl-C ends it."""
    sim_segment_factory(2)
    cfg = _bench(virtual_channel)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    main_thread = threading.main_thread().ident
    assert main_thread is not None

    def operate() -> None:
        bus = open_bus("virtual", virtual_channel, receive_own_messages=False)
        try:
            client = ManagerClient(bus, 100, timeout=1.0)

            def ready() -> bool:
                try:
                    return all(d["phase"] == "READY" for d in client.status()["drives"])
                except NoAnswer:  # the run has not started its node yet
                    return False
            wait_for(ready, "bring-up", DEMO_WAIT)
            client.write(CLEAR, 1)
            client.switch("trajectory", timeout=DEMO_WAIT)
            client.write(ESTOP, 1)
            client.close()
        finally:
            bus.shutdown()
            signal.pthread_kill(main_thread, signal.SIGINT)  # the operator's Ctrl-C
    operator = threading.Thread(target=operate)
    operator.start()
    try:
        assert main(["run", str(path), "--no-flight", "--duration", str(4 * DEMO_WAIT)]) == OK
    finally:
        operator.join(DEMO_WAIT)
    out, err = capfd.readouterr()
    lines = untimed(out)  # (each line has its time: untimed checks it)
    assert err == ""
    node = "SDO (node 100)"
    wanted = [
        "rocoma-can: state FAILPROOF, controller torque_off, e-stop latched (rocoma-can clear "
        "clears it)",
        f"rocoma-can: {node}: clear: the e-stop latch is cleared",
        "rocoma-can: state OK, controller trajectory",
        f"rocoma-can: {node}: switch to 'trajectory': SWITCHED",
        "rocoma-can: e-stop (EMERGENCY): SDO e-stop (0x2110)",
        "rocoma-can: torque-off (FAILPROOF): loop stopping: signal SIGINT"]
    assert [line for line in lines if line in wanted] == wanted, lines
    assert lines[0].startswith("rocoma-can: running 2 drives at 100 Hz")
    assert any(line.startswith("rocoma-can: bring-up finished in ") for line in lines)
    assert lines[-1].startswith("rocoma-can: stopped (signal SIGINT); cycles "), lines


def test_warnings_of_a_start_are_said_once_in_the_consoles_format(tmp_path, capfd):
    """Three drives of one file with no 0x6007 and nothing answering on the bus: the
    note once for the three, the bus's silence once, the end; every line in the one
    format, none in logging's own (``2026-... ERROR rocoma_can.drivers.hardware: ...``)."""
    no_abort = str(TESTS / "fixtures" / "eds" / "no_abort_option.eds")
    cfg = _bench(f"nobody-{tmp_path.name}")
    cfg["drives"] = [{**d, "eds": no_abort} for d in cfg["drives"]] + [
        {**cfg["drives"][0], "name": "joint3", "node_id": 3, "eds": no_abort}]
    cfg["supervision"] = {**cfg.get("supervision", {}), "boot_wait": 0.0, "sdo_timeout": 0.05}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["run", str(path), "--no-flight", "--duration", "2"]) == 1
    out, err = capfd.readouterr()
    errors = untimed(err)
    assert [line.split(": ")[1] for line in errors] == ["warning", "error", "error"], errors
    assert errors[0].startswith("rocoma-can: warning: drives 'joint1', 'joint2', 'joint3': no "
                                "0x6007: on manager loss")
    assert errors[1].startswith(f"rocoma-can: error: no drive answers on nobody-{tmp_path.name}"
                                ": joint1 (node 1), joint2 (node 2), joint3 (node 3) each did "
                                "not answer")
    assert errors[2] == ("rocoma-can: error: bring-up did not finish: 3 of 3 drives failed "
                         "(said above)")
    lines = untimed(out)
    assert any(line.startswith("rocoma-can: bring-up ended in ") for line in lines), lines


def test_the_recording_writers_lines_come_in_runs_format(tmp_path, capfd):
    """The recorder's writer process says what goes wrong on run's stderr, in run's one
    format, naming itself (it said ``rocoma-can writer process: LOGGER: ...``, unstamped)."""
    from rocoma_can.drivers.protocol.joints import JointCommand, JointState
    from rocoma_can.record.recorder import BusToRecord, Recorder

    class Manager:
        active_controller_name = "pd"
        estop_latched = False
    recorder = Recorder(JointState.zeros(2), JointCommand.zeros(2), Manager(), 100.0,
                        [BusToRecord("arm", "vcan0", False)], controllers=["pd"],
                        flight=str(tmp_path / "flight"))  # type: ignore[arg-type]
    recorder._queue.put_nowait("not json")  # a line the writer cannot take
    recorder.close()
    assert untimed(capfd.readouterr().err) == [
        "rocoma-can: warning: writer process: rocoma_can.record.writer: a command it could "
        "not take (Expecting value: line 1 column 1 (char 0)): not json"]
