"""A CanopenHardware + ControllerManager loop over a bus, and tiny controllers, for the driver
tests (fast suite on the virtual bus, vcan suite on SocketCAN, and the SIGKILL subprocess).

The loop runs on the test's own thread, one ``cycle()`` at a time, so a test can act between
cycles exactly like the runtime's loop would (e-stop before update, frames after write).
"""
from __future__ import annotations

import inspect
import math
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass

import can

from rocoma_can import Controller, EmergencyController, ManagerState, TimingSupervision
from rocoma_can.drivers.bringup import CONFIG_ATTEMPTS, Timeouts
from rocoma_can.drivers.cia402 import State402
from rocoma_can.drivers.config import DriveConfig
from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.joints import JointMode
from rocoma_can.drivers.sim.dynamics import JointParams
from rocoma_can.runtime.system import manager_for

MANAGER_NODE_ID = 100
INCREMENTS_PER_REV = 1 << 20  # the simulated drive's 0x608F default
RATED_TORQUE_NM = 1.0         # the simulated drive's 0x6076 default (1000 mNm)


def drive_configs(node_ids: Sequence[int], modes: Sequence[str] = ("csp", "csv", "cst"),
                  **kw) -> list[DriveConfig]:
    return [DriveConfig(name=f"j{n}", node_id=n, increments_per_rev=INCREMENTS_PER_REV,
                        rated_torque_nm=RATED_TORQUE_NM, modes=tuple(modes), **kw)
            for n in node_ids]


@dataclass(frozen=True)
class Can:
    """A bus, the supervision margins its scheduler needs, and the test budgets that follow
    from them. The margins are config (the tests check behaviour, not the margins); every
    wait in a driver test is one of the budgets below, never a bare number of seconds."""
    interface: str
    nodes: tuple[int, ...]   # the simulated drives' node ids
    dt: float
    # CST hold of a 0.2 rad step, closed by the manager's loop: kp, kd, tolerance, settle (s)
    pd: tuple[float, float, float, float]
    heartbeat_ms: int        # the manager's heartbeat period
    drive_heartbeat_ms: int  # the drives' heartbeat period
    tpdo_timeout_cycles: int
    timeouts: Timeouts
    joints: JointParams | None = None  # simulated joints (None: the simulator's defaults)
    sdo_timeout: float = 0.5
    heartbeat_timeout_factor: float = 2.5  # drives' heartbeats supervised at this many periods
    config_workers: int = 4  # drives configured over SDO at once
    consumer_factor: float = 2.0  # the drives' consumer of the manager heartbeat, in periods
    stall: float = 2.0  # the longest the machine may stop a process for (a loaded 2-core host)

    def channel(self, virtual_channel: str) -> str:
        return virtual_channel if self.interface == "virtual" else "vcan0"

    def bring_up_budget(self, drives: int) -> float:
        """Boot wait, every configuration attempt of the slowest worker's queue (a drive that
        never answers: SDO timeout + the pause before the next attempt, each time), NMT
        start, fault reset and shutdown probe."""
        t = self.timeouts
        queue = -(-drives // self.config_workers)
        configure = queue * CONFIG_ATTEMPTS * 3 * self.sdo_timeout
        return t.boot_wait + configure + t.start + 2 * t.reset + self.stall

    def enable_budget(self) -> float:
        """The hardware reports a drive that did not enable within timeouts.enable."""
        return self.timeouts.enable + 10 * self.dt + self.stall

    def detect_budget(self) -> float:
        """The slowest supervision path: missing TPDOs or a drive's heartbeat deadline."""
        return max(self.tpdo_timeout_cycles * self.dt,
                   self.heartbeat_timeout_factor * self.drive_heartbeat_ms / 1000) + self.stall

    def timing(self) -> TimingSupervision:
        """The manager's wall-time supervision, widened to what this machine may stall a
        cycle (``stall``): a preempted initialize_fast or advance on a loaded CI machine is
        not a controller fault. The hang watchdog still fires, after ``stall``."""
        per_dt = self.stall / self.dt
        return TimingSupervision(advance=per_dt, initialize_fast=per_dt, hang=per_dt)

    def hang_budget(self) -> float:
        """The watchdog fires after ``stall`` (``timing``), then sends every dt."""
        return 2 * self.stall + 10 * self.dt

    def recovery_budget(self) -> float:
        return RECOVERY_TIMEOUT + self.stall


RECOVERY_TIMEOUT = inspect.signature(CanopenHardware.recover).parameters["timeout"].default


VIRTUAL = Can("virtual", tuple(range(1, 7)), 0.005, (4.0, 0.3, 0.02, 1.5), 250, 200, 40,
              Timeouts())
# The user-mode-linux guest has one CPU and every system call costs 0.1-0.6 ms (even a clock
# read): six drives at 25 Hz, the loop and the simulator (one process) kept it busy, and a
# thread could lag for a second. Hence three drives at 25 Hz, supervision of about a second
# (TPDOs, the drives' heartbeats, and the drives' consumer of the manager's heartbeat: a
# stall of the test process is a real loss to the drives), SDO answers allowed 2 s, two
# drives configured at a time
# (no burst of SDO traffic on top of the cycle) and longer start-up steps; six drives run in
# the fast suite. A CST PD on the default 0.01 kg m^2 joint is too lively for the guest's
# stalls: ten times the inertia with the drive's loop gains scaled alike (CSP/CSV behave the
# same), a gentler PD (omega ~4.5 rad/s), and the hold is only asserted to pull the joint to
# within half the step: the manager closes that loop itself, so a stall of it shows.
VCAN = Can("socketcan", (1, 2, 3), 0.04, (2.0, 0.6, 0.1, 3.0), 250, 200, 25,
           Timeouts(start=5.0, reset=3.0, enable=3.0),
           JointParams(inertia=0.1, viscous=0.1, velocity_gain=8.0, velocity_integral=80.0),
           sdo_timeout=2.0, heartbeat_timeout_factor=5.0, config_workers=2, consumer_factor=4.0,
           stall=5.0)


class Rig:
    """Hardware + manager on ``bus``; ``cycle()`` is one loop iteration paced at dt."""

    def __init__(self, bus: can.BusABC, node_ids: Sequence[int], dt: float,
                 modes: Sequence[str] = ("csp", "csv", "cst"), *,
                 estop_must_be_cleared: bool = False, manager_heartbeat_ms: int = 100,
                 timeouts: Timeouts = Timeouts(), drive_heartbeat_ms: int = 100,
                 timing: TimingSupervision | None = TimingSupervision(), **hw_kw) -> None:
        self.dt = dt
        drives = drive_configs(node_ids, modes, heartbeat_ms=drive_heartbeat_ms)
        self.hw = CanopenHardware(bus, drives, MANAGER_NODE_ID, dt,
                                  manager_heartbeat_ms=manager_heartbeat_ms,
                                  timeouts=timeouts, **hw_kw)
        self.mgr = manager_for(self.hw, estop_must_be_cleared=estop_must_be_cleared,
                               timing=timing)
        self.states: list[ManagerState] = []
        self._next = time.monotonic()
        self.setup: Can | None = None
        self.hw.start()

    @classmethod
    def for_setup(cls, bus: can.BusABC, node_ids: Sequence[int], setup: Can, **kw) -> Rig:
        """A rig with the setup's rate and supervision margins (``kw`` overrides them)."""
        kw.setdefault("manager_heartbeat_ms", setup.heartbeat_ms)
        kw.setdefault("drive_heartbeat_ms", setup.drive_heartbeat_ms)
        kw.setdefault("tpdo_timeout_cycles", setup.tpdo_timeout_cycles)
        kw.setdefault("timeouts", setup.timeouts)
        kw.setdefault("sdo_timeout", setup.sdo_timeout)
        kw.setdefault("heartbeat_timeout_factor", setup.heartbeat_timeout_factor)
        kw.setdefault("config_workers", setup.config_workers)
        kw.setdefault("consumer_factor", setup.consumer_factor)
        kw.setdefault("timing", setup.timing())
        rig = cls(bus, node_ids, setup.dt, **kw)
        rig.setup = setup
        return rig

    def cycle(self) -> ManagerState:
        now = time.monotonic()
        if now < self._next:
            time.sleep(self._next - now)
        self._next = max(self._next + self.dt, time.monotonic() - self.dt)
        state = self.hw.run_cycle()
        self.states.append(state)
        return state

    def run(self, seconds: float) -> None:
        for _ in range(max(1, int(round(seconds / self.dt)))):
            self.cycle()

    def run_until(self, predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.cycle()
            if predicate():
                return True
        return False

    def switch(self, name: str, timeout: float = 5.0):
        """Switch while the loop keeps cycling (as the runtime's switcher thread does)."""
        future = self.mgr.request_switch(name)
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
            self.cycle()
        return future.result(timeout=0.0)

    def close(self) -> None:
        self.mgr.shutdown()
        self.hw.close()


class HoldPD(Controller):
    """CST PD to ``target`` (default: the pose at initialize)."""

    def __init__(self, name: str = "hold", kp: float = 4.0, kd: float = 0.3,
                 target: float | None = None) -> None:
        super().__init__(name)
        self.kp, self.kd, self.target = kp, kd, target
        self.goal = None

    def initialize(self, dt: float) -> bool:
        self.goal = self.state.position.copy()
        if self.target is not None:
            self.goal.fill(self.target)
        return True

    def advance(self, dt: float) -> bool:
        s, c = self.state, self.command
        c.mode.fill(JointMode.CST)
        c.torque[:] = self.kp * (self.goal - s.position) - self.kd * s.velocity
        return True


class Sine(Controller):
    """Tracks q(t) = start + a sin(2 pi f t) in CSP (position target) or CSV (velocity)."""

    def __init__(self, name: str, mode: JointMode, amplitude: float = 0.3,
                 frequency: float = 0.5, kp: float = 5.0) -> None:
        super().__init__(name)
        self.mode, self.a, self.f, self.kp = mode, amplitude, frequency, kp
        self.t = 0.0
        self.start = None

    def reference(self) -> float:
        return self.a * math.sin(2 * math.pi * self.f * self.t)

    def initialize(self, dt: float) -> bool:
        self.t = 0.0
        self.start = self.state.position.copy()
        return True

    def advance(self, dt: float) -> bool:
        self.t += dt
        c = self.command
        c.mode.fill(self.mode)
        ref = self.start + self.reference()
        if self.mode == JointMode.CSP:
            c.position[:] = ref
        else:
            w = 2 * math.pi * self.f
            c.velocity[:] = (self.a * w * math.cos(w * self.t)
                             + self.kp * (ref - self.state.position))
        return True


class Brake(EmergencyController):
    """Velocity zero in CSV: the smart stop."""

    def __init__(self, name: str = "brake") -> None:
        super().__init__(name)

    def initialize(self, dt: float) -> bool:
        return True

    def initialize_fast(self, dt: float) -> bool:
        return True

    def advance(self, dt: float) -> bool:
        c = self.command
        c.mode.fill(JointMode.CSV)
        c.velocity.fill(0.0)
        c.torque.fill(0.0)
        return True


def seconds_until_all_off(segment, since: float, bound: float) -> float:
    """Seconds from ``since`` until every simulated drive is in switch on disabled (polled,
    at most ``bound`` seconds; it is an assertion failure if they are not by then)."""
    def all_off() -> bool:
        return all(d.state402 == State402.SWITCH_ON_DISABLED for d in segment.drives.values())
    while time.monotonic() - since < bound and not all_off():
        time.sleep(0.005)
    elapsed = time.monotonic() - since
    assert all_off(), segment.status_lines()
    return elapsed


def serve(channel: str, interface: str, node_ids: Sequence[int], heartbeat_ms: int,
          seconds: float) -> None:
    """A manager process for the SIGKILL test (VCAN setup): bring up, enable, print ENABLED,
    keep cycling."""
    bus = can.Bus(interface=interface, channel=channel, receive_own_messages=False,
                  ignore_config=True)
    setup = VCAN if interface == "socketcan" else VIRTUAL
    rig = Rig.for_setup(bus, node_ids, setup, manager_heartbeat_ms=heartbeat_ms)
    try:
        if not rig.run_until(lambda: not rig.hw.starting, setup.bring_up_budget(len(node_ids))):
            raise SystemExit(f"bring-up timed out: {rig.hw.drive_status()}")
        rig.mgr.add_controller(HoldPD())
        rig.switch("hold")
        if not rig.run_until(lambda: rig.hw.all_enabled, setup.enable_budget()):
            raise SystemExit(f"enable timed out: {rig.hw.drive_status()}")
        print("ENABLED", flush=True)
        rig.run(seconds)
    finally:
        rig.close()
        bus.shutdown()


MARKER = 0x7F0  # a COB-ID nothing else uses


def synced_mark(recorder, rig: Rig) -> int:
    """A recorder mark after every frame the rig has sent so far: the recorder reads on a
    thread of its own and may lag, but frames of one sender arrive in order, so once it has
    seen a marker frame sent now, it has seen everything sent before."""
    marker = can.Message(arbitration_id=MARKER, data=struct.pack("<d", time.monotonic()),
                         is_extended_id=False)
    since = recorder.mark()
    rig.hw._canopen.bus.send(marker, timeout=1.0)
    recorder.wait_for(lambda f: f.cob_id == MARKER and f.data == bytes(marker.data),
                      rig.setup.stall, since=since)
    return recorder.mark()
