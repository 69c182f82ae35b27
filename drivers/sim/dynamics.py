"""Joint physics and the drive's own control loops for a whole simulated segment.

Every joint of a segment lives in one set of numpy arrays, so a SYNC steps all of them in a
few vector operations. Units are SI on the joint side (rad, rad/s, Nm); the drives convert
to and from CiA 402 increments and per mille.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

#: How far (as a fraction of ``max_substep``) a step may exceed it and still be taken whole.
SUBSTEP_SLACK = 0.25


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
    (semi-implicit Euler with at most ``max_substep`` seconds per sub-step, give or take
    ``SUBSTEP_SLACK``; with the default JointParams the loops' stability limit, ~25 ms, is
    more than ten times the default). The default takes a 1 kHz SYNC in one sub-step even
    when it comes late (a loaded machine's 1.4 ms, or the longest of four segments' SYNC
    intervals in a joined step); a sub-step costs ~40 numpy calls, a third of what the
    simulator spends per SYNC. Stiffer joints (``velocity_gain / inertia`` above ~100/s)
    want a shorter one.
    """

    def __init__(self, params: list[JointParams], max_substep: float = 0.002) -> None:
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
        # scratch, allocated once: a step allocates nothing
        self._vcmd = np.zeros(n)
        self._tau = np.zeros(n)
        self._acc = np.zeros(n)
        self._vnew = np.zeros(n)
        self._err = np.zeros(n)
        self._tmp = np.zeros(n)
        self._inv_inertia = 1.0 / self.inertia
        self._neg_limit = np.zeros(n)
        self._not_position = np.zeros(n, dtype=bool)
        self._looped = np.zeros(n, dtype=bool)
        self._not_looped = np.zeros(n, dtype=bool)
        self._off = np.zeros(n, dtype=bool)
        self._free = np.zeros(n, dtype=bool)
        self._stick = np.zeros(n, dtype=bool)
        self._mask = np.zeros(n, dtype=bool)
        self._dt = np.zeros(n)            # this step's length per joint (0: not stepped)
        self._h = np.zeros(n)             # and its sub-step's
        self._half_h = np.zeros(n)
        self._stepped = np.zeros(n, dtype=bool)

    @classmethod
    def joined(cls, parts: list[JointDynamics]) -> JointDynamics:
        """One set of arrays for the joints of several parts (in order), stepped in one call;
        every array of each part becomes a view of its slice, so the part still steps its
        own joints alone and its drives read and write them as before. A step of ~35 ufunc
        calls costs about the same for 3 joints as for 12: four 3-joint segments stepped
        together cost a quarter. The caller keeps a part's steps and the whole's apart
        (the simulator: the whole steps only with every part's lock held)."""
        if not parts or len({p.max_substep for p in parts}) != 1:
            raise ValueError("joined dynamics need parts with one max_substep")
        whole = cls.__new__(cls)
        whole.n = sum(p.n for p in parts)
        whole.max_substep = parts[0].max_substep
        for name, value in vars(parts[0]).items():
            if isinstance(value, np.ndarray):
                setattr(whole, name, np.concatenate([getattr(p, name) for p in parts]))
        first = 0
        for part in parts:
            for name, value in vars(whole).items():
                if isinstance(value, np.ndarray):
                    setattr(part, name, value[first:first + part.n])
            first += part.n
        return whole

    def step(self, dt: float | np.ndarray) -> None:
        """Advance ``dt`` seconds: one length for every joint, or one per joint (0: that
        joint is left as it is, as a joined segment whose SYNC did not come)."""
        lengths = self._dt
        np.copyto(lengths, dt)
        longest = float(lengths.max())
        if longest <= 0:
            return
        steps = max(1, math.ceil(longest / self.max_substep - SUBSTEP_SLACK))
        np.maximum(lengths, 0.0, out=lengths)
        np.divide(lengths, steps, out=self._h)
        np.multiply(self._h, 0.5, out=self._half_h)
        np.greater(lengths, 0.0, out=self._stepped)
        # what the modes select, once per step (the drives set mode and limits before it)
        mode = self.mode
        np.not_equal(mode, LoopMode.POSITION, out=self._not_position)
        np.greater_equal(mode, LoopMode.VELOCITY, out=self._looped)
        np.logical_not(self._looped, out=self._not_looped)
        np.equal(mode, LoopMode.OFF, out=self._off)
        np.negative(self.torque_limit, out=self._neg_limit)
        np.logical_and(self._not_looped, self._stepped, out=self._mask)
        np.copyto(self._integral, 0.0, where=self._mask)
        for _ in range(steps):
            self._substep()

    def _substep(self) -> None:
        q, v, tau, vcmd, err, tmp = (self.position, self.velocity, self._tau, self._vcmd,
                                     self._err, self._tmp)
        h = self._h
        limit, neg_limit = self.torque_limit, self._neg_limit
        # velocity command: CSP position loop + feed-forward, or the CSV target
        np.subtract(self.target_position, q, out=vcmd)
        vcmd *= self.kp
        vcmd += self.target_velocity
        np.copyto(vcmd, self.target_velocity, where=self._not_position)
        # velocity loop (PI) for CSP/CSV, torque target for CST, nothing when off
        np.subtract(vcmd, v, out=err)
        np.multiply(self.kv, err, out=tau)
        tau += self._integral
        np.copyto(tau, 0.0, where=self._not_looped)
        tau += self.torque_feedforward
        np.minimum(tau, limit, out=tau)
        np.maximum(tau, neg_limit, out=tau)
        np.copyto(tau, 0.0, where=self._off)
        # anti-windup: integrate only while the output is not saturated
        np.abs(tau, out=tmp)
        np.less(tmp, limit, out=self._free)
        self._free &= self._looped
        np.multiply(self.ki, err, out=tmp)
        tmp *= h
        np.logical_not(self._free, out=self._mask)
        np.copyto(tmp, 0.0, where=self._mask)
        self._integral += tmp
        np.minimum(self._integral, limit, out=self._integral, where=self._stepped)
        np.maximum(self._integral, neg_limit, out=self._integral, where=self._stepped)
        np.copyto(self.torque, tau, where=self._stepped)
        # rigid joint with viscous friction and Coulomb friction that sticks at rest
        acc, vnew = self._acc, self._vnew
        np.multiply(self.viscous, v, out=acc)
        np.subtract(tau, acc, out=acc)
        np.sign(v, out=tmp)
        tmp *= self.coulomb
        acc -= tmp
        acc *= self._inv_inertia
        np.multiply(acc, h, out=vnew)
        vnew += v
        stick, mask = self._stick, self._mask
        np.equal(v, 0.0, out=stick)
        np.abs(tau, out=tmp)
        np.less_equal(tmp, self.coulomb, out=mask)
        stick &= mask
        np.multiply(v, vnew, out=tmp)
        np.less(tmp, 0.0, out=mask)
        stick |= mask
        np.copyto(vnew, 0.0, where=stick)
        np.add(v, vnew, out=tmp)
        tmp *= self._half_h
        q += tmp
        np.copyto(v, vnew)
