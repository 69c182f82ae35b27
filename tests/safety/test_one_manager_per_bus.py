"""A second manager on a bus where one already runs (rocoma_can/runtime/another_manager.py):
it listens before it sends anything, and refuses, naming what it heard. Two real runtimes
on one virtual bus with simulated drives: the first must be untouched (still OK, its drives
enabled, no fault) and the bus must carry no frame of the second."""
from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from fixtures.console import untimed
from fixtures.running import DEMO_RUN, DEMO_WAIT, runtime_running, wait_for

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.main import main
from rocoma_can.drivers.protocol import cia301
from rocoma_can.errors import BusTaken
from rocoma_can.runtime import Runtime
from rocoma_can.runtime.another_manager import (
    LISTEN_PERIODS,
    listen_time,
    watched,
    what_run_listens_for,
)
from rocoma_can.runtime.config import validate

RATE = 100.0


def _config(channel: str, **manager: Any) -> dict[str, Any]:
    cfg = demo_config(channel, drives=2, rate=RATE)
    cfg["manager"].update(estop_must_be_cleared=False, **manager)
    return cfg


def _file(tmp_path: Path, cfg: dict[str, Any]) -> str:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


@contextmanager
def _sending(channel: str, cob_id: int, data: bytes, period: float,
             extended: bool = False) -> Iterator[None]:
    """A third party sending one frame every ``period`` s on ``channel``."""
    bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    stop = threading.Event()

    def send() -> None:
        while not stop.is_set():
            bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=extended))
            stop.wait(period)
    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(DEMO_WAIT)
        bus.shutdown()


def test_a_second_run_on_a_bus_a_manager_drives_refuses_and_sends_nothing(
        virtual_channel, sim_segment_factory, frame_recorder, tmp_path, capsys):
    segment = sim_segment_factory(2)
    recorder = frame_recorder()
    cfg = _config(virtual_channel)
    with runtime_running(cfg, DEMO_RUN) as first:
        wait_for(lambda: first.manager.switch_blocked() is None, "drives up", DEMO_WAIT)
        assert first.manager.switch_controller("pd", timeout=DEMO_WAIT) == SwitchResult.SWITCHED
        wait_for(lambda: first.hardware.all_enabled, "drives enabled", DEMO_WAIT)
        faults = len(first.hardware.fault_events)
        mark, cycles = recorder.mark(), first.loop.stats.cycles
        capsys.readouterr()
        assert main(["run", _file(tmp_path, cfg), "--no-flight", "--duration", "5"]) == 2
        out, err = capsys.readouterr()
        assert out == ""
        [line] = untimed(err)  # one line, in run's console format
        assert line == (
            "rocoma-can: error: another manager is driving the bus: heard within "
            f"{listen_time(validate(cfg)):.3f} s on virtual:{virtual_channel}: SYNC (0x080), "
            "the state frame of manager node 100 (0x1E4), the heartbeat of node 100 (0x764), "
            "this manager's node id, an RPDO to drive 'joint1' (0x201, 0x301), an RPDO to "
            "drive 'joint2' (0x202, 0x302); nothing was sent. Stop it first (rocoma-can "
            f"status --interface virtual --channel {virtual_channel} --node 100 asks it), or "
            "give this config a bus of its own")
        # the first manager untouched: OK, pd, its drives enabled, no fault
        assert first.manager.state is ManagerState.OK
        assert first.manager.active_controller_name == "pd"
        assert first.hardware.all_enabled and len(first.hardware.fault_events) == faults
        assert all(d.state402.name == "OPERATION_ENABLED" for d in segment.drives.values())
        # and no frame of the second: no NMT, no SDO to the drives, no SYNC beyond the
        # first's one per cycle
        nodes = tuple(segment.drives)
        assert not recorder.frames({cia301.NMT} | {cia301.SDO_RX + n for n in nodes},
                                   since=mark)
        syncs = len(recorder.frames(cia301.SYNC, since=mark))
        assert syncs <= first.loop.stats.cycles - cycles + 2


def test_the_runtime_refuses_before_it_builds_anything_that_sends(virtual_channel,
                                                                  sim_segment_factory):
    """In Python as on the command line: BusTaken from the constructor, nothing started."""
    sim_segment_factory(2)
    cfg = _config(virtual_channel)
    with runtime_running(cfg, DEMO_RUN) as first:
        wait_for(lambda: first.manager.switch_blocked() is None, "drives up", DEMO_WAIT)
        second = dict(cfg, zenoh={"prefix": "rocoma/never", "multicast": False})
        threads = set(threading.enumerate())
        with pytest.raises(BusTaken, match="another manager is driving the bus"):
            Runtime(validate(second))
        assert set(threading.enumerate()) <= threads  # nothing of the second left running


@pytest.mark.parametrize("cob_id, data, named", [
    (0x080, b"", "SYNC (0x080)"),
    (0x764, b"\x05", "the heartbeat of node 100 (0x764), this manager's node id"),
    (0x1E4, b"\x02\x01", "the state frame of manager node 100 (0x1E4)"),
    (0x202, b"\x0f\x00\x08\x00\x00\x00\x00\x00", "an RPDO to drive 'joint2' (0x202, 0x302)"),
], ids=["sync", "heartbeat", "state-frame", "rpdo"])
def test_each_sign_of_another_manager_is_enough_and_named(virtual_channel, cob_id, data,
                                                         named):
    cfg = validate(_config(virtual_channel))
    with _sending(virtual_channel, cob_id, data, cfg.manager.heartbeat_ms / 1000):
        with pytest.raises(BusTaken) as refused:
            Runtime(cfg)
    text = str(refused.value)
    assert f"on virtual:{virtual_channel}: {named}; nothing was sent" in text, text


def test_drives_and_other_nodes_on_the_bus_are_no_manager(virtual_channel,
                                                          sim_segment_factory):
    """The drives' boot-ups and heartbeats, another node id's heartbeat, a TPDO, a 29-bit
    frame on an RPDO's identifier: a lone manager starts."""
    sim_segment_factory(2)
    with _sending(virtual_channel, 0x765, b"\x05", 0.02), \
            _sending(virtual_channel, 0x181, bytes(8), 0.01), \
            _sending(virtual_channel, 0x201, bytes(8), 0.01, extended=True):
        with Runtime(validate(_config(virtual_channel))) as rt:
            assert rt.manager.state is ManagerState.FAILPROOF


def test_the_listening_time_is_derived_from_the_config(virtual_channel):
    cfg = validate(_config(virtual_channel))
    assert listen_time(cfg) == pytest.approx(LISTEN_PERIODS * 0.1)  # the heartbeat's
    slow = validate({**_config(virtual_channel, heartbeat_ms=400)})
    assert listen_time(slow) == pytest.approx(LISTEN_PERIODS * 0.4)
    assert listen_time(validate({**_config(virtual_channel), "rate": 2.0})) == \
        pytest.approx(LISTEN_PERIODS * 0.5)  # the loop's period, longer than the heartbeat's


def test_two_buses_each_listened_to_for_its_own_drives(virtual_channel):
    cfg = validate(demo_config(virtual_channel, drives=4, rate=RATE, buses=2))
    ids = watched(cfg)
    left, right = (b.label for b in cfg.buses)
    assert {0x080, 0x764} <= set(ids[left]) and {0x080, 0x764} <= set(ids[right])
    assert 0x201 in ids[left] and 0x201 in ids[right]  # node ids from 1 on each bus
    assert ids[left][0x201] != ids[right][0x201]         # but other drives
    with _sending(f"{virtual_channel}-1", 0x080, b"", 0.01):
        with pytest.raises(BusTaken) as refused:
            Runtime(cfg)
    assert f"on virtual:{virtual_channel}-1: SYNC (0x080)" in str(refused.value)
    assert f"virtual:{virtual_channel}-0:" not in str(refused.value)


def test_check_config_says_how_run_tells(virtual_channel, tmp_path, capsys):
    cfg = _config(virtual_channel)
    assert main(["check-config", _file(tmp_path, cfg)]) == 0
    out = capsys.readouterr().out
    assert f"note: {what_run_listens_for(validate(cfg))}" in out
    assert (f"run listens 0.250 s for another manager (virtual:{virtual_channel}: SYNC 0x080, "
            "node 100's heartbeat 0x764, RPDOs 0x201, 0x202, 0x301, 0x302) and refuses to "
            "start if it hears one; `rocoma-can doctor CONFIG` listens the same way") in out


def test_doctor_hears_a_running_manager_and_fails(virtual_channel, sim_segment_factory,
                                                  tmp_path, capsys):
    sim_segment_factory(2)
    cfg = _config(virtual_channel)
    path = _file(tmp_path, cfg)
    assert main(["doctor", path]) == 0
    out = capsys.readouterr().out
    assert "another manager" in out and "nothing heard" in out, out
    with runtime_running(cfg, DEMO_RUN):
        capsys.readouterr()
        assert main(["doctor", path]) == 1
        out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if "another manager" in line)
    assert line.split()[0] == "FAIL" and "SYNC (0x080)" in line, out
    assert "fix: stop it first" in out
