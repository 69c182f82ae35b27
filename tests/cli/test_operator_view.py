"""rocoma_can/cli/operator_verbs.py, rocoma_can/cli/status_watch.py: what the operator is told and
allowed, through the CLI against a running manager (the real Runtime, simulated drives, python-can's
virtual bus): clearing an e-stop never re-arms a faulted drive, `status` shows every drive, and a
configured subset of drives may run degraded."""
from __future__ import annotations

import json
import threading
import time
from contextlib import contextmanager

import pytest
from fixtures.driver_rig import VIRTUAL
from fixtures.running import runtime_running
from fixtures.running import wait_for as wait_until

from rocoma_can import ManagerState
from rocoma_can.cli.demo.config import MANAGER_ID, demo_config
from rocoma_can.cli.main import main
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402

RATE = 100.0
# Every wait is a budget of the bus setup the demo config shares with the driver tests
# (default supervision, SDO timeout and start-up timeouts; tests/fixtures/driver_rig.py),
# the longest of them: bring-up, which includes SDO retries on a loaded machine.
WAIT = max(VIRTUAL.bring_up_budget(3), VIRTUAL.recovery_budget(), VIRTUAL.enable_budget())


def wait_for(predicate, what: str, timeout: float = WAIT) -> None:
    wait_until(predicate, what, timeout)


@pytest.fixture
def cli(virtual_channel, capsys):
    opts = ["--interface", "virtual", "--channel", virtual_channel, "--node", str(MANAGER_ID),
            "--timeout", "2.0"]

    def run(*args: str) -> tuple[int, str, str]:
        code = main([*args, *opts])
        out, err = capsys.readouterr()
        return code, out, err
    return run


@contextmanager
def running(channel: str, **manager):
    cfg = demo_config(channel, drives=3, rate=RATE)
    cfg["manager"].update(manager)
    with runtime_running(cfg, WAIT) as rt:
        yield rt


def test_clear_never_rearms_a_faulted_drive(virtual_channel, sim_segment_factory, cli):
    segment = sim_segment_factory(3)
    with running(virtual_channel) as rt:
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        assert cli("clear")[0] == 0
        assert cli("switch", "pd")[:2] == (0, "SWITCHED\n")
        wait_for(lambda: rt.hardware.all_enabled, "every drive enabled")

        segment.drives[2].trip_fault(cia301.EMCY_OVERCURRENT)
        wait_for(lambda: rt.manager.state is ManagerState.EMERGENCY, "the e-stop")
        assert cli("failproof")[0] == 0
        wait_for(lambda: all(d.state402 in (State402.SWITCH_ON_DISABLED, State402.FAULT)
                             for d in segment.drives.values()), "every drive off")

        assert cli("clear")[0] == 0  # the latch clears ...
        code, out, err = cli("switch", "pd")  # ... but the faulted drive keeps it refused
        assert (code, out) == (1, "ERROR\n")
        assert "drives not ready: joint2 (fault: " in err and "0x2310" in err, err
        time.sleep(20 / RATE)
        assert rt.manager.state is ManagerState.FAILPROOF
        assert all(d.state402 != State402.OPERATION_ENABLED for d in segment.drives.values())

        code, out, _ = cli("status", "--json")
        status = json.loads(out)
        assert code == 0 and status["state"] == "FAILPROOF" and status["startup_finished"]
        assert status["switch_refused"].startswith("drives not ready: joint2")
        drives = {d["name"]: d for d in status["drives"]}
        assert set(drives) == {"joint1", "joint2", "joint3"}
        assert "0x2310" in drives["joint2"]["fault"] and drives["joint1"]["fault"] is None
        assert all(d["phase"] == "READY" and d["nmt_state"] == "OPERATIONAL"
                   and d["heartbeat_age"] is not None for d in drives.values())

        code, out, _ = cli("status")
        assert code == 0 and "drive joint2 (node 2): READY, FAULT" in out, out

        assert cli("recover")[0] == 0
        wait_for(lambda: rt.manager.switch_blocked() is None, "the recovery")
        assert cli("switch", "pd")[:2] == (0, "SWITCHED\n")
        wait_for(lambda: rt.hardware.all_enabled, "every drive enabled again")


def test_status_before_any_switch_says_none(virtual_channel, sim_segment_factory, cli):
    sim_segment_factory(3)
    with running(virtual_channel) as rt:
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        code, out, _ = cli("status")
        assert code == 0
        assert "last_switch: none" in out and "estop_cause: " in out and "recovery: none" in out


def test_required_drives_run_degraded_without_the_others(virtual_channel, sim_segment_factory,
                                                         cli):
    """Node 2 is not on the bus: with `required_drives` naming the other two, a switch is
    accepted once those are up; joint2 is only ever sent torque-off."""
    segment = sim_segment_factory((1, 3))
    with running(virtual_channel, required_drives=["joint1", "joint3"]) as rt:
        wait_for(lambda: rt.hardware.not_ready([0, 2]) is None, "joint1 and joint3 brought up")
        assert cli("clear")[0] == 0
        assert cli("switch", "pd")[:2] == (0, "SWITCHED\n")
        wait_for(lambda: all(d.state402 == State402.OPERATION_ENABLED
                             for d in segment.drives.values()), "joint1 and joint3 enabled")
        assert not rt.hardware.ready[1]


def test_status_reports_cycle_statistics_bus_load_and_feedback(virtual_channel,
                                                               sim_segment_factory, cli):
    sim_segment_factory(3)
    with running(virtual_channel) as rt:
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        code, out, _ = cli("status", "--json")
        status = json.loads(out)
        assert code == 0 and status["cycle"]["rate"] == RATE and status["cycle"]["cycles"] > 0
        assert status["cycle"]["period_mean_ms"] > 0
        (bus,) = status["buses"]
        assert bus["channel"] == virtual_channel and bus["load"] is None  # in-process
        assert all(isinstance(d[k], float) for d in status["drives"]
                   for k in ("position", "velocity", "torque"))
        code, out, _ = cli("status")
        assert "cycle: " in out and " cycles at 100 Hz, overruns " in out
        assert f"bus {bus['name']} ({virtual_channel}): planned load n/a" in out
        assert "drive joint1 (node 1): READY" in out and ", position +" in out


def test_status_watch_in_a_terminal_shows_the_state_change_of_an_estop(virtual_channel,
                                                                       sim_segment_factory,
                                                                       cli):
    """The live view, drawn by rich on a pseudo-terminal, as in a person's shell: OK with
    pd, then, after `rocoma-can estop`, the e-stop's cause and the state it led to."""
    import os
    import pty
    import select

    import can
    from rich.console import Console

    from rocoma_can.cli.status_watch import watch
    from rocoma_can.node.client import ManagerClient
    sim_segment_factory(3)
    master, slave = pty.openpty()
    screen = b""

    def read_until(text: bytes, what: str) -> None:
        nonlocal screen
        deadline = time.monotonic() + WAIT
        while text not in screen:
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}: {screen[-2000:]!r}")
            if select.select([master], [], [], 0.1)[0]:
                screen += os.read(master, 65536)

    with running(virtual_channel) as rt, open(slave, "w", closefd=True) as terminal:
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        assert cli("clear")[0] == 0 and cli("switch", "pd")[:2] == (0, "SWITCHED\n")
        bus = can.Bus(interface="virtual", channel=virtual_channel, ignore_config=True)
        stop = threading.Event()
        console = Console(file=terminal, force_terminal=True, width=160)
        with ManagerClient(bus, MANAGER_ID, timeout=2.0) as client:
            viewer = threading.Thread(target=watch, args=(client.status, "manager node 100"),
                                      kwargs={"interval": 0.2, "console": console,
                                              "stop": stop})
            viewer.start()
            try:
                read_until(b" OK ", "the view of state OK")
                read_until(b"pd", "the active controller")
                screen = b""
                assert cli("estop")[0] == 0
                read_until(b"SDO e-stop (0x2110)", "the e-stop's cause")
                # the screen that shows the cause shows the state it led to: damp's smart
                # stop (EMERGENCY), or torque-off once damp has brought the joints to rest
                cause = screen.index(b"SDO e-stop (0x2110)")
                shown = screen[screen.rindex(b"state", 0, cause):cause]
                assert b" EMERGENCY " in shown or b" FAILPROOF " in shown, shown
            finally:
                stop.set()
                viewer.join(10.0)
                bus.shutdown()
        assert not viewer.is_alive()
    os.close(master)


def test_status_watch_runs_for_its_duration_and_ends(virtual_channel, sim_segment_factory,
                                                     cli):
    sim_segment_factory(3)
    with running(virtual_channel) as rt:
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        code, out, _ = cli("status", "--watch", "--duration", "1.5")
        assert code == 0 and "FAILPROOF" in out and "drives" in out and "joint3" in out
        code, _, err = cli("status", "--watch", "--interval", "0.2")  # SDO load on the bus
        assert code == 2 and "at least 1 s over SDO" in err


def test_status_view_draws_bring_up_progress_a_pulsing_homing_and_a_stale_manager():
    """The view of a status report as the manager node serves it (0x2140's JSON), while
    drives are being brought up and one is homing, and after the manager stopped answering."""
    from rich.console import Console

    from rocoma_can.cli.status_watch import view
    drive = {"node_id": 1, "cia402_state": "SWITCH_ON_DISABLED", "enabled": False,
             "fault": None, "nmt_state": "PRE-OPERATIONAL", "heartbeat_age": 0.05,
             "homing": "", "position": 0.25, "velocity": None, "torque": None}
    status = {"state": "FAILPROOF", "active": "torque_off", "latched": True,
              "last_switch": "none", "switch_refused": "", "estop_cause": "",
              "estop_cob_id": 0xA0, "startup_finished": False, "recovery": "running",
              "bus_fault": None, "cycle": None, "buses": [],
              "drives": [{**drive, "name": "a", "phase": "READY"},
                         {**drive, "name": "b", "phase": "CONFIGURING", "node_id": 2},
                         {**drive, "name": "c", "phase": "READY", "node_id": 3,
                          "homing": "homing"}]}
    console = Console(record=True, width=160, force_terminal=True)
    console.print(view(status, label="manager node 100"))
    text = console.export_text()
    assert "bring-up" in text and "2/3 ready" in text and "CONFIGURING" in text
    assert "homing: homing" in text and "recovery" in text and "+0.250" in text
    console.print(view(status, problem="no answer from manager node 100", answered=1.0,
                       label="manager node 100"))
    assert "STALE: no answer from manager node 100" in console.export_text()
