"""drivers/sim/dynamics.py: CSP, CSV and CST move the simulated joint as commanded; torque off lets
it coast."""
from __future__ import annotations

import math
import struct
import time
import uuid

import can
import numpy as np
import pytest
from fixtures.driver_rig import VIRTUAL

from rocoma_can.drivers.link.frame_io import FrameReader
from rocoma_can.drivers.protocol.cia402 import Mode, State402
from rocoma_can.drivers.sim.dynamics import JointDynamics, JointParams, LoopMode
from rocoma_can.drivers.sim.segment import RX_IDLE, SimulatedSegment

REV = 2 ** 20  # increments per revolution (0x608F default)
PERIOD = 0.002  # the sim_bench default sync_period


def test_cst_accelerates_like_the_joint_model(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, drive, rec = bench.node(1), bench.drive(1), bench.recorder
    bench.enable(1, Mode.CST)
    node.sdo[0x6071].raw = 500  # per mille of 1 Nm rated
    mark = bench.barrier()  # not rec.mark(): on SocketCAN older TPDOs may still be in flight
    bench.sync(50)
    # J dv/dt = tau - b v - c  ->  v(t) = (tau - c) / b * (1 - exp(-b t / J))
    p = JointParams()
    t = 50 * PERIOD
    expected = (0.5 - p.coulomb) / p.viscous * (1 - math.exp(-p.viscous * t / p.inertia))
    assert drive.velocity_rad_s == pytest.approx(expected, rel=0.01)
    assert drive.torque_nm == pytest.approx(0.5)
    statusword, mode, torque = struct.unpack("<HbH", rec.wait_for_count(50, bench.stall, 0x181,
                                                                        since=mark)[-1].data)
    assert (mode, torque) == (Mode.CST, 500)
    position, velocity = struct.unpack("<ii", rec.wait_for_count(50, bench.stall, 0x281,
                                                                 since=mark)[-1].data)
    assert position == round(drive.position_rad * REV / (2 * math.pi))
    assert velocity == round(drive.velocity_rad_s * REV / (2 * math.pi))


def test_torque_is_limited_by_0x6072(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    node.sdo[0x6072].raw = 800
    bench.enable(1, Mode.CST)
    node.sdo[0x6071].raw = 5000
    bench.sync(3)
    assert drive.torque_nm == pytest.approx(0.8)
    assert drive.torque_per_mille == 800


def test_csv_tracks_the_target_velocity(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, drive = bench.node(1), bench.drive(1)
    bench.enable(1, Mode.CSV)
    node.sdo[0x60FF].raw = REV // 2  # half a revolution per second
    bench.sync(250)
    assert drive.velocity_rad_s == pytest.approx(math.pi, rel=0.005)
    assert drive.velocity_increments == pytest.approx(REV // 2, rel=0.005)
    node.sdo[0x60B1].raw = REV // 2  # velocity offset adds
    bench.sync(250)
    assert drive.velocity_rad_s == pytest.approx(2 * math.pi, rel=0.005)


def test_csp_reaches_the_target_position(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, drive = bench.node(1), bench.drive(1)
    bench.enable(1, Mode.CSP)
    target = round(1.0 * REV / (2 * math.pi))  # 1 rad
    node.sdo[0x607A].raw = target
    bench.sync(500)
    assert drive.position_rad == pytest.approx(1.0, abs=1e-3)
    assert drive.position_increments == pytest.approx(target, abs=200)
    assert abs(drive.velocity_rad_s) < 0.01


def test_mode_switch_on_the_fly(sim_bench):
    bench = sim_bench(1)
    node, drive = bench.node(1), bench.drive(1)
    bench.enable(1, Mode.CSV)
    node.sdo[0x60FF].raw = REV
    bench.sync(200)
    here = drive.position_increments
    node.sdo[0x607A].raw = here
    node.sdo[0x6060].raw = int(Mode.CSP)
    assert node.sdo[0x6061].raw == Mode.CSP
    bench.sync(500)
    assert drive.state402 == State402.OPERATION_ENABLED
    assert abs(drive.velocity_rad_s) < 0.01  # holds where it was told, not where it drifted
    assert drive.position_increments == pytest.approx(here, abs=REV * 0.15)
    node.sdo[0x6060].raw = int(Mode.CST)
    node.sdo[0x6071].raw = -300
    bench.sync(50)
    assert drive.velocity_rad_s < -1.0


def test_disable_voltage_gives_zero_torque_and_the_joint_coasts(sim_bench, sim_interface):
    bench = sim_bench(1, sim_interface)
    node, drive, rec = bench.node(1), bench.drive(1), bench.recorder
    bench.spin(1, REV, syncs=250)
    v0, q0 = drive.velocity_rad_s, drive.position_rad
    node.sdo[0x6040].raw = 0x00
    assert drive.state402 == State402.SWITCH_ON_DISABLED
    mark = bench.barrier()  # TPDOs of the powered SYNCs may still be on their way
    bench.sync(100)
    assert drive.torque_nm == 0.0
    tpdo = rec.wait_for_count(100, bench.stall, 0x181, since=mark)
    assert all(struct.unpack("<HbH", f.data)[2] == 0 for f in tpdo)
    # coasting against friction only: J dv/dt = -b v - c
    p = JointParams()
    t = 100 * PERIOD
    tau = p.inertia / p.viscous
    v_ss = p.coulomb / p.viscous
    expected = (v0 + v_ss) * math.exp(-t / tau) - v_ss
    assert drive.velocity_rad_s == pytest.approx(expected, rel=0.01)
    assert drive.position_rad > q0 + 0.5 * v0 * t


def test_dynamics_vectorised_over_joints_and_stick_friction():
    dyn = JointDynamics([JointParams(), JointParams(inertia=0.1, coulomb=0.5)])
    dyn.mode[:] = LoopMode.TORQUE
    dyn.torque_feedforward[:] = 0.3
    dyn.step(0.1)
    assert dyn.velocity[0] > 0.0
    assert dyn.velocity[1] == 0.0  # 0.3 Nm does not break 0.5 Nm of static friction
    dyn.mode[:] = LoopMode.OFF
    for _ in range(200):
        dyn.step(0.01)
    np.testing.assert_array_equal(dyn.velocity, [0.0, 0.0])  # friction stops it, no jitter
    with pytest.raises(ValueError, match="inertia"):
        JointParams(inertia=0.0)


def test_a_sync_a_hair_over_the_substep_is_one_substep():
    """A 1 kHz SYNC measured at 1.0004 ms is integrated in one sub-step (two doubled the
    simulator's cost on every other SYNC); well past the slack it is two: the velocity loop
    then acts twice, which one step of the same length does not match."""
    def run(dt: float, max_substep: float) -> float:
        dyn = JointDynamics([JointParams(coulomb=0.0)], max_substep=max_substep)
        dyn.mode[:] = LoopMode.VELOCITY
        dyn.target_velocity[:] = 1.0
        dyn.step(dt)
        return float(dyn.position[0])
    assert run(0.0010004, 0.001) == pytest.approx(run(0.0010004, 1.0), rel=1e-12)
    assert run(0.0013, 0.001) != pytest.approx(run(0.0013, 1.0), rel=1e-6)


def _state(parts: list[JointDynamics]) -> np.ndarray:
    return np.concatenate([np.concatenate((p.position, p.velocity, p.torque, p._integral))
                           for p in parts])


@pytest.mark.parametrize("lengths", [(0.001,), (0.0, 0.001), (0.0, 0.0023)],
                         ids=["all-stepped", "some-left", "some-left-substeps"])
def test_joined_dynamics_step_exactly_as_their_parts_alone(lengths):
    """A segment group steps four segments' joints in one call (JointDynamics.joined); a
    segment whose SYNC did not come gets length 0. Every joint must end where its part,
    stepped alone by the same lengths, puts it: random modes, targets and torque limits
    for 300 steps, bit for bit."""
    rng = np.random.default_rng(7)

    def parts() -> list[JointDynamics]:
        return [JointDynamics([JointParams(initial_position=0.1 * k, coulomb=0.02 * k)] * 3)
                for k in range(4)]
    alone, joined_parts = parts(), parts()
    whole = JointDynamics.joined(joined_parts)
    assert whole.n == 12
    assert all(np.shares_memory(p.position, whole.position) for p in joined_parts)
    for _ in range(300):
        mode = rng.integers(int(LoopMode.OFF), int(LoopMode.POSITION) + 1, 12)
        target, limit = rng.normal(size=12), rng.uniform(0.01, 2.0, 12)
        velocity = rng.normal(size=12)
        step = rng.choice(lengths, 4)
        for k in range(4):
            joints = slice(3 * k, 3 * k + 3)
            for part in (alone[k], joined_parts[k]):
                part.mode[:] = mode[joints]
                part.target_position[:] = target[joints]
                part.target_velocity[:] = velocity[joints]
                part.torque_limit[:] = limit[joints]
            alone[k].step(float(step[k]))
        whole.step(np.repeat(step, 3))
    np.testing.assert_array_equal(_state(joined_parts), _state(alone))
    assert np.abs(_state(alone)).max() > 0.1  # the joints moved: the test compares motion


def test_a_segment_free_runs_only_over_a_silence_its_reader_has_seen():
    """Between SYNCs the segment keeps its joints running (``free_run_period``), so a
    joint coasts on after its master is gone; but only over time its reader has seen pass
    without frames. A reader that lags has SYNCs queued, and a free-running step (up to
    ``max_dt`` in sub-steps, under the segment's lock) would only make it lag more. Here
    nobody reads the bus at first: the coasting joint stays where it is while the drive's
    heartbeats (same timer thread, 100 ms) show 200 ms of timers passing; one read of the
    silent bus, and the joint coasts."""
    channel = f"free-run-{uuid.uuid4().hex[:8]}"
    master = can.Bus(interface="inproc", channel=channel, ignore_config=True)
    segment = SimulatedSegment.open(channel, "inproc", (1,), free_run_period=0.01)
    try:
        segment.start(receive=False)  # its reader: this test, which does not read yet
        with segment.lock:
            segment.dynamics.velocity[0] = 5.0  # rad/s; switch on disabled: no torque
        heartbeats = 0
        deadline = time.monotonic() + VIRTUAL.detect_budget()
        while heartbeats < 3:  # boot-up, then two heartbeats 100 ms apart
            assert time.monotonic() < deadline, "the drive's heartbeats"
            msg = master.recv(RX_IDLE)
            heartbeats += msg is not None and msg.arbitration_id == 0x701
        assert segment.drives[1].position_rad == 0.0
        segment.pump(FrameReader(segment.bus), 0.0)  # the bus read: silent
        deadline = time.monotonic() + VIRTUAL.detect_budget()
        while segment.drives[1].position_rad == 0.0:
            assert time.monotonic() < deadline, "the joint coasts once the silence is seen"
            time.sleep(RX_IDLE)
        segment.check()
    finally:
        segment.stop()
        master.shutdown()
