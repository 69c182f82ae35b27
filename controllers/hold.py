"""Hold position (emergency, entry point ``hold``): a stiff PD on the pose at the failure.

A stop of category 2: ``initialize_fast`` captures the measured position in the failure's
cycle and the joints are held there, by the PD here (CST) or by the drives' position loop
(CSP). For robots that must not sag or fall when their controller fails.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState
from rocoma_can.interfaces import EmergencyController

from .joint_group import JointGroup
from .params import output_mode
from .pd_law import PdGains, track
from .pose_swap import PoseSwapState


class Hold(EmergencyController[JointState, JointCommand]):
    """Parameters (per joint: a scalar or one value per selected joint):
      joints        joint names this controller drives (default: all)
      kp, kd        gains, Nm/rad and Nm·s/rad, >= 0 (CST only)
      torque_limit  |torque| bound, Nm, > 0 (default: none)
      mode          "CST" (default) or "CSP"
    """

    feedback_needed = frozenset({"position"})

    def __init__(self, name: str = "hold", *, joints: Sequence[str] | None = None,
                 kp: object = 200.0, kd: object = 5.0, torque_limit: object = math.inf,
                 mode: object = "CST") -> None:
        super().__init__(name)
        self.group = JointGroup(self, joints)
        self._gains = PdGains.check(self, kp, kd, torque_limit)
        self.mode = output_mode(self, mode, (JointMode.CST, JointMode.CSP))

    def create(self, dt: float) -> bool:
        g = self.group
        g.bind(self.state, self.command)
        self.law = self._gains.law(self, g.n)
        self.hold_position = np.zeros(g.n)
        return True

    def initialize_fast(self, dt: float) -> bool:
        self.group.read()
        np.copyto(self.hold_position, self.group.q)
        return True

    def initialize(self, dt: float) -> bool:
        return self.initialize_fast(dt)

    def advance(self, dt: float) -> bool:
        g = self.group
        g.read()
        track(g, self.law, self.mode, self.hold_position, None, None)
        g.write()
        return True

    def get_swap_state(self) -> PoseSwapState:
        """The held pose as reference, so a controller switched to next starts there."""
        g = self.group
        g.read()
        return PoseSwapState(g.names, self.hold_position.copy(), np.zeros(g.n),
                             self.hold_position.copy(), g.q.copy())
