"""A rigid-joint plant for testing controllers without a bus.

Each joint is an inertia with viscous friction: ``I a = tau + disturbance - b v``, integrated
with semi-implicit Euler at ``dt``. The command's mode per joint decides the input, like an
ideal CiA 402 drive: CST applies the torque target (+ disturbance), CSP/CSV track position /
velocity exactly, QUICK_STOP ramps the velocity to zero at ``quick_stop_deceleration`` and
TORQUE_OFF lets the joint coast. It writes the JointState a driver would decode.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from rocoma_can.drivers.cia402 import State402
from rocoma_can.drivers.joints import JointCommand, JointMode, JointState
from rocoma_can.interfaces import Controller
from rocoma_can.workers import WorkerManager


class JointPlant:
    def __init__(self, names: Sequence[str] | int = 12, *, dt: float = 0.001,
                 inertia: float = 0.05, friction: float = 0.1,
                 quick_stop_deceleration: float = 50.0) -> None:
        self.state = JointState.zeros(names)
        self.command = JointCommand.zeros(self.state.names)
        n = self.state.n
        self.dt = dt
        self.inertia = np.full(n, inertia)
        self.friction = np.full(n, friction)
        self.quick_stop_deceleration = quick_stop_deceleration
        self.disturbance = np.zeros(n)  # external torque, Nm (acts unless CSP/CSV hold it)
        self.time = 0.0
        self.state.cia402_state.fill(State402.OPERATION_ENABLED)
        self.state.fresh.fill(True)

    def set(self, position: Sequence[float] | float = 0.0,
            velocity: Sequence[float] | float = 0.0) -> None:
        self.state.position[:] = position
        self.state.velocity[:] = velocity

    def step(self) -> None:
        """Apply the current command for one dt."""
        s, c, dt = self.state, self.command, self.dt
        q, v = s.position, s.velocity
        mode = c.mode
        torque = np.where(mode == JointMode.CST, c.torque, 0.0)
        free = (mode == JointMode.CST) | (mode == JointMode.TORQUE_OFF)
        acc = (torque + self.disturbance - self.friction * v) / self.inertia
        v_free = v + acc * dt
        quick = mode == JointMode.QUICK_STOP
        dv = self.quick_stop_deceleration * dt
        v_quick = np.sign(v) * np.maximum(np.abs(v) - dv, 0.0)
        csp = mode == JointMode.CSP
        csv = mode == JointMode.CSV
        v_new = np.select([free, quick, csv, csp],
                          [v_free, v_quick, c.velocity, (c.position - q) / dt], v)
        q_new = np.where(csp, c.position, q + v_new * dt)
        s.position[:] = q_new
        s.velocity[:] = v_new
        s.torque[:] = np.where(csp | csv, c.torque, torque)
        s.cia402_state[:] = np.select(
            [mode == JointMode.TORQUE_OFF, quick],
            [State402.SWITCH_ON_DISABLED, State402.QUICK_STOP_ACTIVE],
            State402.OPERATION_ENABLED)
        self.time += dt
        s.time = self.time

    def run(self, advance: Callable[[float], object], steps: int) -> None:
        """``steps`` cycles of: controller advance (reads state, writes command), plant step."""
        for _ in range(steps):
            if advance(self.dt) is False:
                raise AssertionError(f"advance failed at t={self.time:.3f}s")
            self.step()


def attach(controller, plant: JointPlant, dt: float | None = None):
    """Do what the manager does before create: set dt, state, command and workers."""
    controller.dt = plant.dt if dt is None else dt
    if isinstance(controller, Controller):
        controller.workers = WorkerManager(controller.name)
    controller.state = plant.state
    controller.command = plant.command
    return controller
