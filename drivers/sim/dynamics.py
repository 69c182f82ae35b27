"""Joint physics and the drive's own control loops for a whole simulated segment.

Every joint of a segment lives in one set of numpy arrays (the drives write their commands
into them and read their joints back; a SegmentGroup joins several segments' into one).
A step reads them once as Python floats and integrates joint by joint, where the same
step as ~50 numpy calls on the arrays costs a fixed amount whatever the count, more than a
dozen joints cost one by one (a dozen drives share a CAN bus at 1 kHz; numpy pays only for
several times that). Units are SI
on the joint side (rad, rad/s, Nm); the drives convert to and from CiA 402 increments and
per mille.
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


_OFF, _VELOCITY, _POSITION = int(LoopMode.OFF), int(LoopMode.VELOCITY), int(LoopMode.POSITION)


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
    intervals in a joined step). Stiffer joints (``velocity_gain / inertia`` above ~100/s)
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
        self.velocity_limit = np.full(n, np.inf)  # bounds the velocity loop's command
        self._dt = np.zeros(n)            # this step's length per joint (0: not stepped)

    @classmethod
    def joined(cls, parts: list[JointDynamics]) -> JointDynamics:
        """One set of arrays for the joints of several parts (in order), stepped in one call;
        every array of each part becomes a view of its slice, so the part still steps its
        own joints alone and its drives read and write them as before. A step's fixed part
        (reading and writing the arrays, ~20 numpy calls) is then paid once for all parts.
        The caller keeps a part's steps and the whole's apart
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
        joint is left as it is, as a joined segment whose SYNC did not come).

        Per joint and sub-step: the velocity command (CSP: position loop + feed-forward;
        CSV: the target) within +-``velocity_limit``, the PI velocity loop (CSP/CSV; CST:
        the torque target alone; OFF: nothing) plus the torque offset, limited to
        +-``torque_limit``; the integral grows only while the output is not saturated
        (anti-windup) and is cleared when no velocity loop runs; then the rigid joint with
        viscous friction and Coulomb friction that sticks at rest (semi-implicit Euler,
        position by the mean velocity)."""
        lengths = self._dt
        np.copyto(lengths, dt)
        dts = lengths.tolist()
        longest = max(dts)
        if longest <= 0:
            return
        steps = max(1, math.ceil(longest / self.max_substep - SUBSTEP_SLACK))
        position, velocity, torque, integral_of = (
            self.position.tolist(), self.velocity.tolist(), self.torque.tolist(),
            self._integral.tolist())
        mode_of, target_position, target_velocity, feedforward, limit_of, vlimit_of = (
            self.mode.tolist(), self.target_position.tolist(), self.target_velocity.tolist(),
            self.torque_feedforward.tolist(), self.torque_limit.tolist(),
            self.velocity_limit.tolist())
        kp_of, kv_of, ki_of, viscous_of, coulomb_of, inertia_of = (
            self.kp.tolist(), self.kv.tolist(), self.ki.tolist(), self.viscous.tolist(),
            self.coulomb.tolist(), self.inertia.tolist())
        for j, length in enumerate(dts):
            if length <= 0.0:
                continue
            h = length / steps
            half_h = h * 0.5
            mode, limit, vlimit = mode_of[j], limit_of[j], vlimit_of[j]
            looped = mode >= _VELOCITY
            q, v = position[j], velocity[j]
            integral = integral_of[j] if looped else 0.0
            kp, kv, ki, viscous, coulomb = kp_of[j], kv_of[j], ki_of[j], viscous_of[j], \
                coulomb_of[j]
            inv_inertia = 1.0 / inertia_of[j]
            qt, vt, tff = target_position[j], target_velocity[j], feedforward[j]
            tau = 0.0
            for _ in range(steps):
                vcmd = (qt - q) * kp + vt if mode == _POSITION else vt
                vcmd = -vlimit if vcmd < -vlimit else vlimit if vcmd > vlimit else vcmd
                err = vcmd - v
                tau = (kv * err + integral if looped else 0.0) + tff
                tau = -limit if tau < -limit else limit if tau > limit else tau
                if mode == _OFF:
                    tau = 0.0
                if looped and abs(tau) < limit:
                    integral += ki * err * h
                integral = -limit if integral < -limit else limit if integral > limit \
                    else integral
                friction = coulomb if v > 0.0 else -coulomb if v < 0.0 else 0.0
                vnew = (tau - viscous * v - friction) * inv_inertia * h + v
                if (v == 0.0 and abs(tau) <= coulomb) or v * vnew < 0.0:
                    vnew = 0.0  # static friction holds, or it stops the joint
                q += (v + vnew) * half_h
                v = vnew
            position[j], velocity[j], torque[j], integral_of[j] = q, v, tau, integral
        self.position[:] = position
        self.velocity[:] = velocity
        self.torque[:] = torque
        self._integral[:] = integral_of
