"""Joint PD / impedance control to a target pose (entry point ``pd``).

The reference moves from where the controller took over towards the target at most
``velocity_limit`` rad/s per joint (a step when infinite), so a switch or a new target does
not kick the robot. In CST the PD runs here (torque = kp e + kd ė + ff, clipped to
``torque_limit``); in CSP the drive closes the loop on the reference (velocity offset =
reference velocity, torque offset = feedforward).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState
from rocoma_can.interfaces import Controller, SwapState

from .joint_group import JointGroup
from .params import optional_per_joint, output_mode, param_error, per_joint
from .pd_law import PdGains, track
from .pose_swap import PoseSwapState, find_pose_state


class JointPD(Controller[JointState, JointCommand]):
    """PD to a target pose.

    Parameters (per-joint ones take a scalar or one value per selected joint):
      joints          joint names this controller drives (default: all)
      kp, kd          gains, Nm/rad and Nm·s/rad, >= 0 (CST only; CSP uses the drive's loop)
      target          target pose, rad (default: the position at initialize, i.e. hold)
      feedforward     constant torque added, Nm (CST: added to the PD; CSP: torque offset)
      torque_limit    |torque| bound, Nm, > 0 (default: none)
      velocity_limit  reference speed bound, rad/s, > 0 (default: none, the reference steps)
      position_min, position_max   the target is clipped into these, rad
      mode            "CST" (default) or "CSP"
    """

    def __init__(self, name: str = "pd", *, joints: Sequence[str] | None = None,
                 kp: object = 50.0, kd: object = 2.0, target: object = None,
                 feedforward: object = 0.0,
                 torque_limit: object = math.inf, velocity_limit: object = math.inf,
                 position_min: object = -math.inf, position_max: object = math.inf,
                 mode: object = "CST") -> None:
        super().__init__(name)
        self.group = JointGroup(self, joints)
        self._gains = PdGains.check(self, kp, kd, torque_limit)
        self._p_target = optional_per_joint(self, "target", target)
        self._p_ff = per_joint(self, "feedforward", feedforward)
        self._p_velocity_limit = per_joint(self, "velocity_limit", velocity_limit,
                                           positive=True, allow_inf=True)
        self._p_min = per_joint(self, "position_min", position_min, allow_inf=True)
        self._p_max = per_joint(self, "position_max", position_max, allow_inf=True)
        self.mode = output_mode(self, mode, (JointMode.CST, JointMode.CSP))
        # in CST the PD runs here on the joint velocity; in CSP the drive's own loop does
        self.feedback_needed = frozenset(
            {"position", "velocity"} if self.mode == JointMode.CST else {"position"})
        self._pending: tuple[int, np.ndarray] | None = None  # (sequence, target) from set_target
        self._sequence = 0           # last set_target
        self._applied_sequence = 0   # last target the cycle took over

    # --- set-up (not in the cycle) -------------------------------------------------------
    def create(self, dt: float) -> bool:
        g = self.group
        g.bind(self.state, self.command)
        n = g.n
        self.law = self._gains.law(self, n)
        self.feedforward = self._p_ff.resolve(self, n)
        self.velocity_limit = self._p_velocity_limit.resolve(self, n)
        self.position_min = self._p_min.resolve(self, n)
        self.position_max = self._p_max.resolve(self, n)
        bad = np.flatnonzero(self.position_min > self.position_max)
        if bad.size:
            raise param_error(self, "position_min",
                              f"exceeds position_max for joints {[g.names[i] for i in bad]}")
        self._target_param = None if self._p_target is None else self._p_target.resolve(self, n)
        # Reference rate limiting: a step's velocity is only fed forward where it is bounded.
        self._ramped = np.isfinite(self.velocity_limit).astype(float)
        self.target = np.zeros(n)
        self.reference = np.zeros(n)
        self.reference_velocity = np.zeros(n)
        self._step = np.zeros(n)
        self._step_max = np.zeros(n)
        self._step_min = np.zeros(n)
        return True

    def initialize(self, dt: float) -> bool:
        g = self.group
        g.read()
        np.copyto(self.reference, g.q)
        self.reference_velocity.fill(0.0)
        np.copyto(self.target, g.q if self._target_param is None else self._target_param)
        self._clip_target(self.target)
        self._pending = None
        return True

    def swap(self, dt: float, swap_state: SwapState | None) -> bool:
        """Start the reference where the predecessor's reference was (bumpless)."""
        if not self.initialize(dt):
            return False
        pose = find_pose_state(swap_state)
        if pose is not None:
            pose.fill("reference", self.group.names, self.reference)
            if self._target_param is None:  # "hold" means hold the handed-over reference
                pose.fill("reference", self.group.names, self.target)
                self._clip_target(self.target)
        return True

    def get_swap_state(self) -> PoseSwapState:
        self.group.read()
        return PoseSwapState(self.group.names, self.reference.copy(),
                             self.reference_velocity.copy(), self.target.copy(),
                             self.group.q.copy())

    def set_target(self, target: object) -> None:
        """Set a new target pose from any thread; the cycle picks it up at its next advance."""
        values = per_joint(self, "target", target).resolve(self, self.group.n)
        self._clip_target(values)
        self._sequence += 1
        self._pending = (self._sequence, values)  # one assignment: atomic for the cycle

    def _clip_target(self, target: np.ndarray) -> None:
        np.minimum(target, self.position_max, out=target)
        np.maximum(target, self.position_min, out=target)

    # --- the cycle ----------------------------------------------------------------------
    def advance(self, dt: float) -> bool:
        pending = self._pending
        if pending is not None and pending[0] != self._applied_sequence:
            self._applied_sequence = pending[0]
            np.copyto(self.target, pending[1])
        self._move_reference(dt)
        g = self.group
        g.read()
        track(g, self.law, self.mode, self.reference, self.reference_velocity,
              self.feedforward)
        g.write()
        return True

    def _move_reference(self, dt: float) -> None:
        step, hi, lo = self._step, self._step_max, self._step_min
        np.multiply(self.velocity_limit, dt, out=hi)
        np.negative(hi, out=lo)
        np.subtract(self.target, self.reference, out=step)
        np.minimum(step, hi, out=step)
        np.maximum(step, lo, out=step)
        np.add(self.reference, step, out=self.reference)
        np.multiply(step, self._ramped, out=self.reference_velocity)
        np.divide(self.reference_velocity, dt, out=self.reference_velocity)
