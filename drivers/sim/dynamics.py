"""Joint physics and the drive's own control loops for a whole simulated segment.

Every joint of a segment lives in one set of numpy arrays, so a SYNC steps all of them in a
few vector operations. Units are SI on the joint side (rad, rad/s, Nm); the drives convert
to and from CiA 402 increments and per mille.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class LoopMode(enum.IntEnum):
    """Which loop produces a joint's torque in this step."""
    OFF = 0       # power stage off: zero torque, the joint coasts
    TORQUE = 1    # torque target (+ offset)
    VELOCITY = 2  # velocity loop on a velocity target (+ offsets)
    POSITION = 3  # position loop feeding the velocity loop


@dataclass(frozen=True)
class JointParams:
    """Physical joint and the drive's loop gains (joint side, SI units)."""
    inertia: float = 0.01             # kg m^2
    viscous: float = 0.01             # Nm / (rad/s)
    coulomb: float = 0.02             # Nm
    position_gain: float = 40.0       # 1/s: velocity command per rad of position error
    velocity_gain: float = 0.8        # Nm / (rad/s)
    velocity_integral: float = 8.0    # Nm / rad (integral of the velocity error)
    initial_position: float = 0.0     # rad

    def __post_init__(self) -> None:
        if self.inertia <= 0:
            raise ValueError(f"JointParams.inertia must be > 0, got {self.inertia}")
        for name in ("viscous", "coulomb", "position_gain", "velocity_gain",
                     "velocity_integral"):
            if getattr(self, name) < 0:
                raise ValueError(f"JointParams.{name} must be >= 0, got {getattr(self, name)}")


class JointDynamics:
    """Rigid joints with viscous and Coulomb friction, driven by torque-limited loops.

    The step is sub-divided so the velocity loop stays stable whatever the SYNC period
    (semi-implicit Euler with at most ``max_substep`` seconds per sub-step).
    """

    def __init__(self, params: list[JointParams], max_substep: float = 0.001) -> None:
        n = len(params)
        self.n = n
        self.max_substep = max_substep
        self.inertia = np.array([p.inertia for p in params])
        self.viscous = np.array([p.viscous for p in params])
        self.coulomb = np.array([p.coulomb for p in params])
        self.kp = np.array([p.position_gain for p in params])
        self.kv = np.array([p.velocity_gain for p in params])
        self.ki = np.array([p.velocity_integral for p in params])
        # state
        self.position = np.array([p.initial_position for p in params])
        self.velocity = np.zeros(n)
        self.torque = np.zeros(n)        # applied (limited) torque of the last sub-step
        self._integral = np.zeros(n)
        # command, written by the drives before each step
        self.mode = np.zeros(n, dtype=np.int8)
        self.target_position = np.zeros(n)
        self.target_velocity = np.zeros(n)  # CSV target, or CSP velocity feed-forward
        self.torque_feedforward = np.zeros(n)  # CST target, or CSP/CSV torque offset
        self.torque_limit = np.full(n, np.inf)
        # scratch, allocated once
        self._vcmd = np.zeros(n)
        self._tau = np.zeros(n)
        self._acc = np.zeros(n)
        self._vnew = np.zeros(n)

    def step(self, dt: float) -> None:
        if dt <= 0:
            return
        steps = max(1, int(np.ceil(dt / self.max_substep)))
        h = dt / steps
        looped = self.mode >= LoopMode.VELOCITY
        self._integral[~looped] = 0.0
        for _ in range(steps):
            self._substep(h, looped)

    def _substep(self, h: float, looped: np.ndarray) -> None:
        q, v, tau, vcmd = self.position, self.velocity, self._tau, self._vcmd
        # velocity command: CSP position loop + feed-forward, or the CSV target
        np.subtract(self.target_position, q, out=vcmd)
        vcmd *= self.kp
        vcmd += self.target_velocity
        np.copyto(vcmd, self.target_velocity, where=self.mode != LoopMode.POSITION)
        # velocity loop (PI) for CSP/CSV, torque target for CST, nothing when off
        err = vcmd - v
        np.multiply(self.kv, err, out=tau)
        tau += self._integral
        np.copyto(tau, 0.0, where=~looped)
        tau += self.torque_feedforward
        np.clip(tau, -self.torque_limit, self.torque_limit, out=tau)
        np.copyto(tau, 0.0, where=self.mode == LoopMode.OFF)
        # anti-windup: integrate only while the output is not saturated
        free = looped & (np.abs(tau) < self.torque_limit)
        self._integral += np.where(free, self.ki * err * h, 0.0)
        np.clip(self._integral, -self.torque_limit, self.torque_limit, out=self._integral)
        np.copyto(self.torque, tau)
        # rigid joint with viscous friction and Coulomb friction that sticks at rest
        acc, vnew = self._acc, self._vnew
        np.subtract(tau, self.viscous * v, out=acc)
        acc -= self.coulomb * np.sign(v)
        acc /= self.inertia
        np.multiply(acc, h, out=vnew)
        vnew += v
        stick = ((v == 0.0) & (np.abs(tau) <= self.coulomb)) | (v * vnew < 0.0)
        np.copyto(vnew, 0.0, where=stick)
        q += 0.5 * (v + vnew) * h
        np.copyto(v, vnew)
