"""drivers/plan/limits.py, drivers/cycle/command.py (limit_command): drive-side limits (``limits:``)
over a real python-can bus against simulated drives: bring-up writes them and reads them back, a
drive that refuses or keeps another value fails its bring-up naming the object, the manager clips
commands to the same limits and e-stops on a following error, and a drive's own 0x607D stops it at
the limit with the manager gone.

Runs on python-can's virtual bus (fast suite) and on SocketCAN vcan0 (vcan suite)."""
from __future__ import annotations

import math
import re
import time
from pathlib import Path

from fixtures.driver_rig import INCREMENTS_PER_REV, bring_up, enable_with

from rocoma_can import Controller, ManagerState, eds
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.protocol.joints import JointMode

PER_RAD = INCREMENTS_PER_REV / (2 * math.pi)
LIMITS = {"position": [-0.5, 0.8], "velocity": 3.0, "torque": 0.5, "following_error": 0.2}


class Target(Controller):
    """One constant target from the first cycle on: ``position`` (CSP, relative to the pose
    at initialize) or ``velocity`` (CSV)."""

    def __init__(self, mode: JointMode, value: float) -> None:
        super().__init__("target")
        self.mode, self.value = mode, value
        self.start = None

    def initialize(self, dt: float) -> bool:
        self.start = self.state.position.copy()
        return True

    def advance(self, dt: float) -> bool:
        c = self.command
        c.mode.fill(self.mode)
        if self.mode == JointMode.CSP:
            c.position[:] = self.start + self.value
        else:
            c.velocity.fill(self.value)
        return True


def _eds_with(tmp_path: Path, index: int, extra: str) -> str:
    """The shipped EDS with ``extra`` lines added to object ``index``'s section."""
    text = Path(eds.path(eds.CIA402_DRIVE)).read_text()
    section = f"[{index:04X}]\n"
    assert section in text.replace("\r\n", "\n")
    text = text.replace("\r\n", "\n").replace(section, section + extra + "\n")
    path = tmp_path / "drive.eds"
    path.write_text(text)
    return str(path)


def test_bring_up_writes_the_limits_and_the_drive_holds_them(segment, make_rig, can_setup):
    rig = make_rig(drive={"limits": LIMITS})
    bring_up(rig)
    assert rig.hw.all_ready, rig.hw.drive_status()
    timeout_ms = math.ceil(2 * 3 * can_setup.dt * 1000 - 1e-6)  # twice the manager's 3 cycles
    for drive in segment.drives.values():
        assert drive.od_value(0x607D, 1) == math.floor(-0.5 * PER_RAD)
        assert drive.od_value(0x607D, 2) == math.ceil(0.8 * PER_RAD)
        assert drive.od_value(0x607F) == math.ceil(3.0 * PER_RAD)
        assert drive.od_value(0x6080) == 29  # 3 rad/s = 28.6 motor rpm, rounded up
        assert drive.od_value(0x6072) == 500  # per mille of the 1 Nm rated torque
        assert drive.od_value(0x6065) == math.ceil(0.2 * PER_RAD)
        assert drive.od_value(0x6066) == timeout_ms


def test_a_drive_that_refuses_a_limit_fails_its_bring_up_naming_the_object(
        can_setup, make_rig, sim_segment_factory, virtual_channel, tmp_path):
    path = _eds_with(tmp_path, 0x6072, "HighLimit=300")  # refuses 500 per mille
    sim_segment_factory(can_setup.nodes, channel=can_setup.channel(virtual_channel),
                        interface=can_setup.interface, eds_path=path, sync_period=can_setup.dt)
    rig = make_rig(drive={"limits": {"torque": 0.5}, "eds": path})
    bring_up(rig)
    for s in rig.hw.drive_status():
        assert s.phase == "FAILED", s
        assert "0x6072" in s.fault and "refused" in s.fault, s.fault


def test_a_drive_that_keeps_another_value_fails_its_bring_up_with_both(
        segment, make_rig, monkeypatch):
    """A firmware that clamps 0x607F to its own maximum, silently: the read-back finds it."""
    for drive in segment.drives.values():
        objects = drive.objects
        original = objects._on_write

        def clamping(key, value, objects=objects, original=original):
            if key == (0x607F, 0):
                objects.values[key] = min(value, 1000)
            original(key, value)
        monkeypatch.setattr(objects, "_on_write", clamping)
    rig = make_rig(drive={"limits": {"velocity": 3.0}})
    bring_up(rig)
    written = math.ceil(3.0 * PER_RAD)
    for s in rig.hw.drive_status():
        assert s.phase == "FAILED", s
        assert f"0x607F written {written}" in s.fault and "read back 1000" in s.fault, s.fault


def test_the_manager_clips_commands_to_the_same_limits(segment, make_rig):
    nodes = segment.drives
    rig = make_rig(modes=("csp",), drive={"limits": {"position": [-0.5, 0.3]}})
    bring_up(rig)
    enable_with(rig, Target(JointMode.CSP, 2.0))  # far beyond the limit
    rig.run(10 * rig.dt)
    for drive in nodes.values():  # what reached the drive is the limit, not the target
        assert drive.od_value(0x607A) == round(0.3 * PER_RAD)
    assert rig.mgr.state == ManagerState.OK


def test_a_following_error_beyond_the_window_is_an_e_stop_naming_it(segment, make_rig):
    rig = make_rig(modes=("csp",), drive={"limits": {"following_error": 0.05,
                                                    "following_error_cycles": 3}})
    bring_up(rig)
    # a 0.4 rad step: the joint lags far beyond 0.05 rad for many cycles
    enable_with(rig, Target(JointMode.CSP, 0.4))
    assert rig.run_until(lambda: rig.mgr.state != ManagerState.OK,
                         rig.setup.cycles_budget(50)), rig.hw.drive_status()
    faults = [s.fault for s in rig.hw.drive_status() if s.fault]
    assert faults, rig.hw.drive_status()
    assert all(re.search(r"following error 0\.\d+ rad beyond the window 0\.05 rad for 3 cycles",
                         f) for f in faults), faults


def test_a_position_limit_stops_a_drive_with_the_manager_gone(
        can_setup, make_rig, sim_segment_factory, virtual_channel):
    """CSV towards the limit, then the manager vanishes (no frame more, as a crash): the
    drive runs on its last target until its heartbeat consumer switches it off, and its own
    0x607D stops it at the limit meanwhile. Free-running drives (no fixed SYNC period): a
    real drive's loops do not wait for the master."""
    segment = sim_segment_factory(can_setup.nodes[:1], channel=can_setup.channel(virtual_channel),
                                  interface=can_setup.interface, params=can_setup.joints)
    limit = 0.3
    rig = make_rig(nodes=can_setup.nodes[:1], modes=("csv",),
                   drive={"limits": {"position": [-limit, limit]}})
    bring_up(rig)
    enable_with(rig, Target(JointMode.CSV, 0.5))
    drive = segment.drives[can_setup.nodes[0]]
    assert drive.position_rad < limit  # moving, not there yet: the manager goes now
    gone = time.monotonic()  # no cycle more: no frame from the manager, not even torque-off
    # the drive's consumer expires within its consumer time (plus a stall of this process)
    deadline = gone + can_setup.consumer_factor * can_setup.heartbeat_ms / 1000 + can_setup.stall
    furthest = drive.position_rad
    while drive.state402 == State402.OPERATION_ENABLED and time.monotonic() < deadline:
        furthest = max(furthest, drive.position_rad)
        time.sleep(0.005)
    furthest = max(furthest, drive.position_rad)
    assert drive.state402 != State402.OPERATION_ENABLED  # the consumer switched it off
    # 0.5 rad/s for the consumer time would be far beyond it; the drive held the limit
    assert (can_setup.consumer_factor * can_setup.heartbeat_ms / 1000) * 0.5 > 2 * limit
    assert limit - 0.02 < furthest <= limit + 0.02, furthest

