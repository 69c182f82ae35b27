"""Drive quick stop (emergency, entry point ``quick_stop``): CiA 402 quick stop per joint.

The drives brake on their own ramp (0x6085 quick stop deceleration, behaviour after the stop
from option code 0x605A), which keeps working even if this process stalls after sending the
command. Optionally the power stage is switched off ``torque_off_after`` seconds later.
"""
from __future__ import annotations

from collections.abc import Sequence

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState
from rocoma_can.interfaces import EmergencyController

from .joint_group import JointGroup
from .params import number


class QuickStop(EmergencyController[JointState, JointCommand]):
    """Parameters:
      joints            joint names this controller drives (default: all)
      torque_off_after  seconds after which the joints are switched to torque-off, > 0
                        (default: None, stay in quick stop)
    """

    def __init__(self, name: str = "quick_stop", *, joints: Sequence[str] | None = None,
                 torque_off_after: object = None) -> None:
        super().__init__(name)
        self.group = JointGroup(self, joints)
        self.torque_off_after = (None if torque_off_after is None else
                                 number(self, "torque_off_after", torque_off_after,
                                        positive=True))
        self._elapsed = 0.0

    def create(self, dt: float) -> bool:
        self.group.bind(self.state, self.command)
        return True

    def initialize_fast(self, dt: float) -> bool:
        g = self.group
        g.read()
        g.set_mode(JointMode.QUICK_STOP)
        g.position[:] = g.q  # a drive leaving quick stop in CSP would start here
        g.velocity.fill(0.0)
        g.torque.fill(0.0)
        self._elapsed = 0.0
        return True

    def initialize(self, dt: float) -> bool:
        return self.initialize_fast(dt)

    def advance(self, dt: float) -> bool:
        self._elapsed += dt
        if self.torque_off_after is not None and self._elapsed >= self.torque_off_after:
            self.group.torque_off()
        self.group.write()
        return True
