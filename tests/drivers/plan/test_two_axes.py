"""drivers/plan/config.py, drive_plan.py (two axes in one node): two axes in one node (CiA 402-2, as
Roboteq's dual-channel controllers): each axis is a drive entry with `axis: n`, its profile objects
at + (n - 1) x 0x800 in the node's dictionary (tests/fixtures/eds/two_axes.eds). The node's PDO
channels are shared out between its axes, its lowest axis configures the node (NMT, heartbeat,
consumer), and each axis's faults stay its own.

The planning tests need no bus; the others run the real driver against a simulated
two-axis node on python-can's virtual bus (fast suite) and on SocketCAN vcan0 (vcan suite).
"""
from __future__ import annotations

import dataclasses
import math
import time

import pytest
from fixtures.driver_rig import Rig
from fixtures.paths import TESTS
from fixtures.rig_controllers import Brake

from rocoma_can import Controller, ManagerState, SwitchResult
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_clashes import check_drives
from rocoma_can.drivers.plan.drive_plan import plan_drive, plan_drives
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.protocol.joints import JointMode
from rocoma_can.runtime.config import ConfigError, validate

TWO_AXES = str(TESTS / "fixtures" / "eds" / "two_axes.eds")
MODES = ("csp", "csv")  # what the fixture's 0x6502 / 0x6D02 say


def axes(node: int = 1, **kw) -> list[DriveConfig]:
    return [DriveConfig(f"a{n}", node, 4096, 1.0, eds=TWO_AXES, axis=n, modes=MODES, **kw)
            for n in (1, 2)]


# --- planning, without a bus ----------------------------------------------------------------
def test_the_axes_share_the_nodes_channels_out_and_the_lowest_leads():
    first, second = plan_drives(axes())
    assert first.leads_node and not second.leads_node
    own = [{(p.number, p.cob_id) for p in plan.layout.rpdos + plan.layout.tpdos}
           for plan in (first, second)]
    assert not own[0] & own[1]  # no channel, no COB-ID twice
    # each bring-up sees only its own channels (the leader also those nobody uses)
    assert {ch.number for ch in second.caps.rpdos} == {p.number for p in second.layout.rpdos}
    assert {ch.number for ch in first.caps.rpdos} >= {p.number for p in first.layout.rpdos}
    # each axis is read at axis 1's indices: its own 0x6D02, its own objects
    assert second.caps.axis == 2 and second.caps.supports(8) and second.caps.supports(9)
    assert "a2 (node 1 axis 2," in second.report()[0]


def test_the_axes_listed_higher_first_plan_alike():
    reversed_plans = plan_drives(list(reversed(axes())))
    assert [p.drive.axis for p in reversed_plans] == [2, 1]
    assert reversed_plans[1].leads_node and not reversed_plans[0].leads_node


def test_an_axis_the_file_lacks_is_refused_naming_its_controlword():
    with pytest.raises(ValueError, match=r"has no axis 3: no 0x7040 \(axis 3's controlword"):
        plan_drive(DriveConfig("a3", 1, 4096, 1.0, eds=TWO_AXES, axis=3, modes=MODES))
    with pytest.raises(ValueError, match=r"axis must be an integer 1\.\.8"):
        DriveConfig("a9", 1, 4096, 1.0, axis=9)


def test_an_axis_with_no_channel_left_is_refused_saying_who_took_them():
    every = frozenset((tx, n) for tx in (False, True) for n in (1, 2, 3, 4))
    with pytest.raises(ValueError, match=r"no RPDOs left for axis 2: the node's other axes "
                                         r"use RPDO1, RPDO2, RPDO3, RPDO4"):
        plan_drive(axes()[1], taken=every)


def test_one_node_is_one_node_for_what_belongs_to_it():
    a1, a2 = axes()
    check_drives([a1, a2], 100)  # two axes of node 1: fine
    with pytest.raises(ValueError, match=r"node_id 1 axis 2 is already used by drive 'a2'"):
        check_drives([a1, a2, dataclasses.replace(a2, name="again")], 100)
    with pytest.raises(ValueError, match=r"node 1 is also drive 'a1' \(axis 1\), whose "
                                         r"heartbeat_ms is 100, not 50: one node has one "
                                         r"heartbeat_ms"):
        check_drives([a1, dataclasses.replace(a2, heartbeat_ms=50)], 100)


def _config(drives: list[dict]) -> dict:
    return {"bus": {"interface": "virtual", "channel": "two-axes", "bitrate": 1_000_000},
            "rate": 100, "manager": {"node_id": 100},
            "drives": drives,
            "controllers": [{"name": "pd", "plugin": "pd", "params": {"mode": "CSP"},
                             "emergency": "hold"}],
            "emergency_controllers": [{"name": "hold", "plugin": "hold"}]}


def test_check_config_plans_the_axes_of_a_node_together():
    entry = {"node_id": 1, "eds": TWO_AXES, "increments_per_rev": 4096,
             "rated_torque_nm": 1.0, "modes": list(MODES)}
    config = validate(_config([{"name": "left", **entry},
                               {"name": "right", "axis": 2, **entry}]))
    assert [d.axis for d in config.drives] == [1, 2]
    with pytest.raises(ConfigError) as info:
        validate(_config([{"name": "left", **entry},
                          {"name": "right", "axis": 2, **entry, "guarding": "heartbeat",
                           "heartbeat_ms": 50}]))
    assert any("one node has one heartbeat_ms" in p for p in info.value.problems), \
        info.value.problems


# --- on a bus, against a simulated two-axis node --------------------------------------------
@pytest.fixture
def two_axes(can_setup, virtual_channel, sim_segment_factory, bus_factory):
    """A simulated node 1 with two axes and a rig driving both (joints a1, a2)."""
    rigs: list[Rig] = []

    def make(**kw):
        channel = can_setup.channel(virtual_channel)
        segment = sim_segment_factory([1], channel=channel, interface=can_setup.interface,
                                      eds_path=TWO_AXES, params=can_setup.joints,
                                      sync_period=can_setup.dt, axes={1: 2})
        bus = bus_factory(channel, can_setup.interface)
        rig = Rig.for_setup(bus, [1], can_setup, modes=MODES, axes=(1, 2),
                            drive={"eds": TWO_AXES}, **kw)
        rigs.append(rig)
        return segment, rig

    yield make
    for rig in rigs:
        rig.close()


class SecondMoves(Controller):
    """CSP: axis 1 held where it was, axis 2 swung by a sine (the joints apart)."""

    def initialize(self, dt: float) -> bool:
        self.start = self.state.position.copy()
        self.t = 0.0
        return True

    def advance(self, dt: float) -> bool:
        self.t += dt
        c = self.command
        c.mode.fill(JointMode.CSP)
        c.position[:] = self.start
        c.position[1] += 0.2 * math.sin(2 * math.pi * 0.5 * self.t)
        return True


def _bring_up_and_run(rig: Rig) -> None:
    budget = rig.setup.bring_up_budget(len(rig.hw.drives_config))
    assert rig.run_until(lambda: not rig.hw.starting, budget), rig.hw.drive_status()
    assert rig.hw.all_ready, rig.hw.drive_status()
    rig.mgr.add_controller(SecondMoves("second"), emergency=Brake())
    assert rig.switch("second") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, rig.setup.enable_budget()), \
        rig.hw.drive_status()


def test_each_axis_is_mapped_on_its_own_channels_and_moves_alone(two_axes):
    segment, rig = two_axes()
    _bring_up_and_run(rig)
    node = segment.drives[1]
    first, second = node.axes
    assert node.nmt_state == cia301.NmtState.OPERATIONAL
    # axis 2's RPDO carries axis 2's controlword (0x6840), mapped by the driver
    rpdo = rig.hw.plans[1].layout.rpdos[0]
    assert node.od_value(cia301.RPDO_MAP + rpdo.number - 1, 1) >> 16 == 0x6840
    tpdo = rig.hw.plans[1].layout.tpdos[0]
    assert node.od_value(cia301.TPDO_MAP + tpdo.number - 1, 1) >> 16 == 0x6841
    start = (first.position_rad, second.position_rad)
    swing = [0.0, 0.0]
    for _ in range(round(2.0 / rig.dt)):  # one period of the sine
        rig.cycle()
        swing = [max(swing[0], abs(first.position_rad - start[0])),
                 max(swing[1], abs(second.position_rad - start[1]))]
    assert rig.mgr.state == ManagerState.OK
    assert first.state402 == second.state402 == State402.OPERATION_ENABLED
    assert swing[1] > 0.1 and swing[0] < 0.01, swing  # it swings, the other holds
    # and the manager reads each axis's own feedback
    assert abs(rig.hw.state.position[1] - second.position_rad) < 0.05


def test_a_fault_of_one_axis_is_that_axis_s_fault(two_axes):
    segment, rig = two_axes()
    _bring_up_and_run(rig)
    segment.drives[1].axes[1].trip_fault(cia301.EMCY_FOLLOWING_ERROR)
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget()), rig.hw.drive_status()
    latched = rig.hw.supervisor.latched
    assert latched[0] is None and latched[1] is not None, latched
    assert latched[1].drive == "j1.2" and "statusword fault bit" in latched[1].cause
    # recovery resets that axis; the node and its other axis are left running
    future = rig.hw.recover()
    assert rig.run_until(future.done, rig.setup.recovery_budget())
    assert future.result() is True, rig.hw.drive_status()
    # the other axis was not restarted: the emergency layer kept it enabled throughout
    assert segment.drives[1].axes[0].state402 == State402.OPERATION_ENABLED
    assert rig.hw.drive_status()[0].phase == "READY"


def test_torque_off_reaches_every_axis_and_a_dead_loop_switches_both_off(two_axes):
    segment, rig = two_axes()
    _bring_up_and_run(rig)
    rig.mgr.failproof_stop("test")
    axes_ = segment.drives[1].axes
    assert rig.run_until(lambda: all(a.state402 == State402.SWITCH_ON_DISABLED
                                     for a in axes_), rig.setup.detect_budget())
    assert rig.switch("second") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, rig.setup.enable_budget())
    stopped = time.monotonic()  # no more cycles: each axis's 0x6007 / 0x6807 acts
    bound = rig.hw.consumer_ms / 1000 + rig.hw.manager_heartbeat_period + rig.setup.stall
    deadline = stopped + bound
    while time.monotonic() < deadline and not all(
            a.state402 == State402.SWITCH_ON_DISABLED for a in axes_):
        time.sleep(0.005)
    assert all(a.state402 == State402.SWITCH_ON_DISABLED for a in axes_), \
        segment.status_lines()
