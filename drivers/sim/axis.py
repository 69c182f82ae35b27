"""One CiA 402 axis of a simulated node: its objects, factor group, state machine, joint.

A node (drive.py) has one to eight of these (CiA 402-2): axis n's objects at +0x800 (n - 1)
in the node's values (objects.AxisKeys), its own factor group and CiA 402 state machine
(state_machine.py), and its own joint of the segment's dynamics. Each step it samples its
joint into its actual-value objects the way a drive's counters do.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..protocol import cia301 as c301
from ..protocol import cia402 as c
from ..protocol.cia301 import nmt_name
from ..protocol.cia402 import State402
from .dynamics import JointDynamics
from .faults import InjectedFaults
from .objects import AxisKeys
from .state_machine import FactorGroup, StateMachine402

if TYPE_CHECKING:
    from .drive import SimulatedDrive

# 0x6064 (INTEGER32) wraps like a drive's position counter; 0x606C (INTEGER32) and 0x6077
# (INTEGER16) saturate
_HALF32, _SPAN32, _HALF16 = 1 << 31, 1 << 32, 1 << 15


class SimulatedAxis:
    """One CiA 402 axis of a node (``segment.drives[node_id].axes``): its objects
    (``keys``: axis n's 0x6000-0x67FF at +0x800 (n - 1)), its factor group, its state
    machine and its joint. The properties are safe to read from any thread; ``trip_fault``
    takes the segment lock, as the node's does."""

    def __init__(self, node: SimulatedDrive, number: int, joint: int, *,
                 dynamics: JointDynamics, faults: InjectedFaults, rng: np.random.Generator,
                 on_fault_reset: Callable[[], None]) -> None:
        """``node``: the drive it is an axis of; ``dynamics``, ``faults``, ``rng``: its
        segment's joints, its injected faults, its noise; ``on_fault_reset``: the node's
        reaction to this axis's fault reset."""
        self.node = node
        self.number = number
        self.joint = joint
        self.keys = AxisKeys.of(number)
        self._values = node.objects.values
        self._dyn = dynamics
        self._faults = faults
        self._rng = rng
        self.scaling = FactorGroup(self.keys)
        self.cia402 = StateMachine402(joint, self._dyn, self._values, self.scaling, node.emcy,
                                      self._faults, self.keys, on_fault_reset)

    # ------------------------------------------------------------------ read-only view
    @property
    def state402(self) -> State402:
        return self.cia402.state

    @property
    def statusword(self) -> int:
        return int(self._values[self.keys.statusword])

    @property
    def controlword(self) -> int:
        return int(self._values[self.keys.controlword])

    @property
    def mode_display(self) -> int:
        return int(self._values[self.keys.mode_display])

    @property
    def error_code(self) -> int:
        return int(self._values[self.keys.error_code])

    @property
    def position_increments(self) -> int:
        return int(self._values[self.keys.position])

    @property
    def velocity_increments(self) -> int:
        return int(self._values[self.keys.velocity])

    @property
    def torque_per_mille(self) -> int:
        return int(self._values[self.keys.torque])

    @property
    def position_rad(self) -> float:
        """True joint position (no sensor noise)."""
        return float(self._dyn.position[self.joint])

    @property
    def velocity_rad_s(self) -> float:
        return float(self._dyn.velocity[self.joint])

    @property
    def torque_nm(self) -> float:
        """Joint torque the power stage applied in the last step."""
        return float(self._dyn.torque[self.joint])

    @property
    def increments_per_rad(self) -> float:
        """Joint radians to position increments (the axis's 0x608F and 0x6091)."""
        return self.scaling.increments_per_rad

    @property
    def nm_per_permille(self) -> float:
        """Joint torque of one per mille of rated torque (the axis's 0x6076, gear ratio)."""
        return self.scaling.nm_per_permille

    def status_line(self) -> str:
        node = self.node
        try:
            mode = c.Mode(self.mode_display).name
        except ValueError:
            mode = str(self.mode_display)
        f = self._faults
        flags = "".join((" STO" if node.sto_low else "", " SILENT" if f.silent else "",
                         " NO-SYNC" if not f.answer_sync else ""))
        axis = f" axis {self.number}" if len(node.axes) > 1 else ""
        return (f"node {node.node_id:3d}{axis} {nmt_name(node.nmt_state):15s} "
                f"{self.state402.name:22s} sw=0x{self.statusword:04X} mode={mode:4s} "
                f"pos={self.position_rad:+9.4f} rad vel={self.velocity_rad_s:+9.4f} rad/s "
                f"torque={self.torque_nm:+7.3f} Nm err=0x{self.error_code:04X}{flags}")

    def update_units(self) -> None:
        """The factor group or a limit object changed: the joint-side numbers anew."""
        self.scaling.update(self._values)
        self.cia402.limits.update(self.scaling.increments_per_rad,
                                  self.scaling.motor_revs_per_rad)

    def trip_fault(self, code: int = c301.EMCY_GENERIC) -> None:
        """An internal fault of this axis: the node's EMCY with ``code``, this axis's
        0x603F, fault reaction, then FAULT; the other axes run on."""
        self.node.trip_fault(code, axis=self.number)

    # ------------------------------------------------------------------ each step
    def sample(self, position: list[float], velocity: list[float],
               torque: list[float]) -> None:
        """Actual values from the joint's (rad, rad/s, Nm): integer counters wrap like a
        drive's do, velocity and torque saturate at their object's range."""
        j = self.joint
        values = self._values
        keys = self.keys
        per_rad = self.scaling.increments_per_rad
        q = position[j] * per_rad + self.cia402.position_offset
        if self._faults.position_noise:
            q += float(self._rng.normal(0.0, self._faults.position_noise))
        values[keys.position] = (round(q) + _HALF32) % _SPAN32 - _HALF32
        values[keys.velocity] = max(-_HALF32, min(_HALF32 - 1, round(velocity[j] * per_rad)))
        values[keys.torque] = max(-_HALF16, min(
            _HALF16 - 1, round(torque[j] / self.scaling.nm_per_permille)))
