"""Float (entry point ``float``): zero torque, CST with torque 0 on every selected joint.

The drives stay enabled and the joints move freely (back-drivable, no gravity compensation):
for teaching by hand and for measuring friction. Unlike torque-off, the power stage is on, so
the next controller takes over without re-enabling the drives.
"""
from __future__ import annotations

from collections.abc import Sequence

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState
from rocoma_can.interfaces import Controller

from .joint_group import JointGroup


class Float(Controller[JointState, JointCommand]):
    """Parameters:
      joints   joint names this controller drives (default: all)
    """

    def __init__(self, name: str = "float", *, joints: Sequence[str] | None = None) -> None:
        super().__init__(name)
        self.group = JointGroup(self, joints)

    def create(self, dt: float) -> bool:
        self.group.bind(self.state, self.command)
        self.group.set_mode(JointMode.CST)  # torque, position, velocity buffers stay 0
        return True

    def initialize(self, dt: float) -> bool:
        return True

    def advance(self, dt: float) -> bool:
        self.group.write()
        return True
