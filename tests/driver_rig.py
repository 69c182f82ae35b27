"""A CanopenHardware + ControllerManager loop over a bus, and tiny controllers, for the driver
tests (fast suite on the virtual bus, vcan suite on SocketCAN, and the SIGKILL subprocess).

The loop runs on the test's own thread, one ``cycle()`` at a time, so a test can act between
cycles exactly like the runtime's loop would (e-stop before update, frames after write).
"""
from __future__ import annotations

import math
import time
from typing import Sequence

import can

from rocoma_can import Controller, EmergencyController, ManagerState
from rocoma_can.drivers.bringup import Timeouts
from rocoma_can.drivers.cia402 import State402
from rocoma_can.drivers.config import DriveConfig
from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.joints import JointMode

MANAGER_NODE_ID = 100
INCREMENTS_PER_REV = 1 << 20  # the simulated drive's 0x608F default
RATED_TORQUE_NM = 1.0         # the simulated drive's 0x6076 default (1000 mNm)


def drive_configs(node_ids: Sequence[int], modes: Sequence[str] = ("csp", "csv", "cst"),
                  **kw) -> list[DriveConfig]:
    return [DriveConfig(name=f"j{n}", node_id=n, increments_per_rev=INCREMENTS_PER_REV,
                        rated_torque_nm=RATED_TORQUE_NM, modes=tuple(modes), **kw)
            for n in node_ids]


class Rig:
    """Hardware + manager on ``bus``; ``cycle()`` is one loop iteration paced at dt."""

    def __init__(self, bus: can.BusABC, node_ids: Sequence[int], dt: float,
                 modes: Sequence[str] = ("csp", "csv", "cst"), *,
                 estop_must_be_cleared: bool = False, manager_heartbeat_ms: int = 100,
                 timeouts: Timeouts = Timeouts(), drive_heartbeat_ms: int = 100,
                 **hw_kw) -> None:
        self.dt = dt
        drives = drive_configs(node_ids, modes, heartbeat_ms=drive_heartbeat_ms)
        self.hw = CanopenHardware(bus, drives, MANAGER_NODE_ID, dt,
                                  manager_heartbeat_ms=manager_heartbeat_ms,
                                  timeouts=timeouts, **hw_kw)
        self.mgr = self.hw.create_manager(estop_must_be_cleared=estop_must_be_cleared)
        self.states: list[ManagerState] = []
        self._next = time.monotonic()
        self.hw.start()

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
            c.velocity[:] = self.a * w * math.cos(w * self.t) + self.kp * (ref - self.state.position)
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


def serve(channel: str, interface: str, node_ids: Sequence[int], dt: float,
          heartbeat_ms: int, seconds: float) -> None:
    """A manager process for the SIGKILL test: bring up, enable, print ENABLED, keep cycling."""
    bus = can.Bus(interface=interface, channel=channel, receive_own_messages=False,
                  ignore_config=True)
    rig = Rig(bus, node_ids, dt, manager_heartbeat_ms=heartbeat_ms)
    try:
        if not rig.run_until(lambda: not rig.hw.starting, 20.0):
            raise SystemExit(f"bring-up timed out: {rig.hw.drive_status()}")
        rig.mgr.add_controller(HoldPD())
        rig.switch("hold")
        if not rig.run_until(lambda: rig.hw.all_enabled, 10.0):
            raise SystemExit(f"enable timed out: {rig.hw.drive_status()}")
        print("ENABLED", flush=True)
        rig.run(seconds)
    finally:
        rig.close()
        bus.shutdown()
