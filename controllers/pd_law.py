"""The joint-space PD law and the CST/CSP tracking step shared by pd, hold and trajectory.

``torque = clip(kp * (r - q) + kd * (dr - v) + ff, -limit, limit)``, computed in place into
the caller's buffer so the cycle allocates nothing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rocoma_can.drivers.protocol.joints import JointMode

from .joint_group import JointGroup
from .params import Owner, PerJoint, per_joint


@dataclass(frozen=True)
class PdGains:
    """The ``kp``, ``kd`` and ``torque_limit`` parameters, checked at construction."""
    kp: PerJoint
    kd: PerJoint
    torque_limit: PerJoint

    @classmethod
    def check(cls, owner: Owner, kp: object, kd: object, torque_limit: object) -> PdGains:
        return cls(per_joint(owner, "kp", kp, minimum=0.0),
                   per_joint(owner, "kd", kd, minimum=0.0),
                   per_joint(owner, "torque_limit", torque_limit, positive=True,
                             allow_inf=True))

    def law(self, owner: Owner, n: int) -> PdLaw:
        """The law for ``n`` joints (raises ValueError for a list of another length)."""
        return PdLaw(self.kp.resolve(owner, n), self.kd.resolve(owner, n),
                     self.torque_limit.resolve(owner, n))


class PdLaw:
    """Per-joint gains and torque limit, with the scratch buffers of one evaluation."""

    def __init__(self, kp: np.ndarray, kd: np.ndarray, torque_limit: np.ndarray) -> None:
        self.kp = kp
        self.kd = kd
        self.limit = torque_limit
        self._neg_limit = np.negative(torque_limit)
        self._error = np.zeros_like(kp)
        self._damping = np.zeros_like(kp)

    def torque(self, reference: np.ndarray, reference_velocity: np.ndarray | None,
               position: np.ndarray, velocity: np.ndarray,
               feedforward: np.ndarray | None, out: np.ndarray) -> np.ndarray:
        """Write the clipped PD torque into ``out``; a None reference velocity means 0."""
        e, d = self._error, self._damping
        np.subtract(reference, position, out=e)
        np.multiply(self.kp, e, out=out)
        if reference_velocity is None:
            np.negative(velocity, out=d)
        else:
            np.subtract(reference_velocity, velocity, out=d)
        np.multiply(self.kd, d, out=d)
        np.add(out, d, out=out)
        if feedforward is not None:
            np.add(out, feedforward, out=out)
        np.minimum(out, self.limit, out=out)
        np.maximum(out, self._neg_limit, out=out)
        return out


def track(group: JointGroup, law: PdLaw, mode: JointMode, reference: np.ndarray,
          reference_velocity: np.ndarray | None, feedforward: np.ndarray | None) -> None:
    """Fill the group's command buffers so its joints track (r, ṙ) in ``mode``.

    CST runs the PD here (the position target carries the measured position, so a later
    switch to CSP starts where the joint is); CSP hands r to the drive's own loop, with ṙ as
    velocity offset and the feedforward as torque offset. Call ``group.read()`` first.
    """
    group.set_mode(mode)
    if mode == JointMode.CST:
        law.torque(reference, reference_velocity, group.q, group.v, feedforward,
                   out=group.torque)
        np.copyto(group.position, group.q)
        group.velocity.fill(0.0)
        return
    np.copyto(group.position, reference)
    if reference_velocity is None:
        group.velocity.fill(0.0)
    else:
        np.copyto(group.velocity, reference_velocity)
    if feedforward is None:
        group.torque.fill(0.0)
    else:
        np.copyto(group.torque, feedforward)
