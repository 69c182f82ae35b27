"""The subset of joints one controller drives, with its gather/scatter buffers.

A controller of a ControllerTuple drives only some joints (the ``joints`` parameter), so it
works on compact arrays of its own joints: ``read`` gathers the measured position/velocity
from the shared JointState and ``write`` scatters its command buffers into the shared
JointCommand. Indices and buffers are computed once in ``bind`` (from the controller's
create); ``read``/``write`` use ``take``/``put`` with out=/preallocated operands, so they
allocate no arrays in the cycle.
"""
from __future__ import annotations

import numpy as np

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState

from .params import Owner, joint_names, param_error


class JointGroup:
    """Measured ``position``/``velocity`` in, ``mode``/``position``/``velocity``/``torque``
    command buffers out, all of length ``n`` in the order of ``names``."""

    def __init__(self, owner: Owner, joints: object) -> None:
        """``joints``: the controller's ``joints`` parameter, checked here (None: all)."""
        self._owner = owner
        self._requested = joint_names(owner, joints)
        self.names: tuple[str, ...] = ()
        self.n = 0

    def bind(self, state: JointState, command: JointCommand) -> None:
        """Resolve the joint names against the manager's state; raises ValueError."""
        owner = self._owner
        if tuple(state.names) != tuple(command.names):
            raise ValueError(f"{type(owner).__name__} {owner.name!r}: state joints "
                             f"{list(state.names)} differ from command joints "
                             f"{list(command.names)}")
        names = self._requested if self._requested is not None else tuple(state.names)
        unknown = [name for name in names if name not in state.names]
        if unknown:
            raise param_error(owner, "joints", f"unknown joints {unknown}; the robot has "
                                               f"{list(state.names)}")
        self.names = names
        self.n = len(names)
        self.index = np.array([state.names.index(name) for name in names], dtype=np.intp)
        self._state = state
        self._command = command
        self.q = np.zeros(self.n)   # measured position (after read)
        self.v = np.zeros(self.n)   # measured velocity (after read)
        self.mode = np.full(self.n, JointMode.TORQUE_OFF, dtype=np.uint8)
        self.position = np.zeros(self.n)
        self.velocity = np.zeros(self.n)
        self.torque = np.zeros(self.n)

    def read(self) -> None:
        """Gather this group's measured position and velocity into ``q`` and ``v``."""
        # mode="clip": indices were checked in bind; "raise" would buffer the output.
        np.take(self._state.position, self.index, out=self.q, mode="clip")
        np.take(self._state.velocity, self.index, out=self.v, mode="clip")

    def write(self) -> None:
        """Scatter the command buffers into the shared JointCommand."""
        command, index = self._command, self.index
        command.mode.put(index, self.mode, mode="clip")
        command.position.put(index, self.position, mode="clip")
        command.velocity.put(index, self.velocity, mode="clip")
        command.torque.put(index, self.torque, mode="clip")

    def set_mode(self, mode: JointMode) -> None:
        self.mode.fill(mode)

    def torque_off(self) -> None:
        """This group only: power stage off, targets zero (as JointCommand.torque_off)."""
        self.mode.fill(JointMode.TORQUE_OFF)
        self.position.fill(0.0)
        self.velocity.fill(0.0)
        self.torque.fill(0.0)
