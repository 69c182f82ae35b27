"""Damping stop (emergency, entry point ``damp``): brake, then torque-off once still.

A stop of category 1: a velocity-proportional braking torque (CST) takes the energy out of a
moving robot instead of letting it coast, and once every joint has stayed slower than
``still_velocity`` for ``still_time`` the power stage is switched off (a timeout can force
that). Needs no model and no position reference, so it is safe to start from any state.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState
from rocoma_can.interfaces import EmergencyController

from .joint_group import JointGroup
from .params import number, per_joint


class Damp(EmergencyController[JointState, JointCommand]):
    """Parameters:
      joints          joint names this controller drives (default: all)
      damping         braking gain, Nm·s/rad, > 0 (torque = -damping * velocity), per joint
      torque_limit    |torque| bound, Nm, > 0, per joint (default: none)
      still_velocity  |velocity| below which a joint counts as still, rad/s, > 0
      still_time      how long all joints must be still before torque-off, s, >= 0
      timeout         torque-off after this many seconds even if not still, s, > 0
                      (default: never; the joints keep being damped)
    """

    feedback_needed = frozenset({"velocity"})

    def __init__(self, name: str = "damp", *, joints: Sequence[str] | None = None,
                 damping: object = 1.0, torque_limit: object = math.inf,
                 still_velocity: object = 0.05, still_time: object = 0.2,
                 timeout: object = math.inf) -> None:
        super().__init__(name)
        self.group = JointGroup(self, joints)
        self._p_damping = per_joint(self, "damping", damping, positive=True)
        self._p_torque_limit = per_joint(self, "torque_limit", torque_limit, positive=True,
                                         allow_inf=True)
        self.still_velocity = number(self, "still_velocity", still_velocity, positive=True)
        self.still_time = number(self, "still_time", still_time, minimum=0.0)
        self.timeout = number(self, "timeout", timeout, positive=True, allow_inf=True)
        self.torque_is_off = False
        self._still_for = 0.0
        self._elapsed = 0.0

    def create(self, dt: float) -> bool:
        g = self.group
        g.bind(self.state, self.command)
        self.damping = self._p_damping.resolve(self, g.n)
        self.torque_limit = self._p_torque_limit.resolve(self, g.n)
        self._neg_limit = np.negative(self.torque_limit)
        self._speed = np.zeros(g.n)
        return True

    def initialize_fast(self, dt: float) -> bool:
        self.torque_is_off = False
        self._still_for = 0.0
        self._elapsed = 0.0
        self.group.set_mode(JointMode.CST)
        self.group.velocity.fill(0.0)
        return True

    def initialize(self, dt: float) -> bool:
        return self.initialize_fast(dt)

    def advance(self, dt: float) -> bool:
        g = self.group
        if not self.torque_is_off:
            g.read()
            self._elapsed += dt
            np.abs(g.v, out=self._speed)
            if self._speed.max() < self.still_velocity:
                self._still_for += dt
                rested = self._still_for >= self.still_time
            else:
                self._still_for = 0.0
                rested = False
            if rested or self._elapsed >= self.timeout:
                self.torque_is_off = True
                g.torque_off()
            else:
                np.multiply(self.damping, g.v, out=g.torque)
                np.negative(g.torque, out=g.torque)
                np.minimum(g.torque, self.torque_limit, out=g.torque)
                np.maximum(g.torque, self._neg_limit, out=g.torque)
                np.copyto(g.position, g.q)
        g.write()
        return True
