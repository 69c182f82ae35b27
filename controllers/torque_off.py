"""The failproof layer: safe torque-off for every joint.

The CAN hardware layer always installs this one and sends pre-encoded disable-voltage frames
while the manager is in FAILPROOF, whatever this writes; writing the command as well keeps the
shared JointCommand truthful for loggers and for the next controller's swap.
"""
from __future__ import annotations

from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.interfaces import FailproofController


class TorqueOff(FailproofController[JointState, JointCommand]):
    """Every joint: CiA 402 disable voltage, all targets zero."""

    def __init__(self, name: str = "torque_off") -> None:
        super().__init__(name)

    def advance(self, dt: float) -> None:
        self.command.torque_off()
