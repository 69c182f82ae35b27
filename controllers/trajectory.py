"""Trajectory follower: a sine per joint, or a minimum-jerk move to a pose (``trajectory``).

Both kinds are one formula: the reference blends from the start pose ``p0`` into a goal
signal ``g(t)`` with the minimum-jerk profile ``s`` (s(0) = 0, s(T) = 1, ṡ = 0 at both ends):

    r(t) = p0 + s(t/T) (g(t) - p0)        ṙ(t) = ṡ (g - p0) + s ġ

``min_jerk``: g = target, T = duration (a rest-to-rest move). ``sine``:
g = offset + amplitude sin(2π frequency t + phase), T = blend_time, so the reference starts at
rest at ``p0`` and is on the sine after T, with continuous position and velocity.
``p0`` is the predecessor's reference when it hands over a PoseSwapState (the PD does), else
the measured position: the switch is bumpless. Output: CSP (drive tracks r, velocity offset ṙ)
or CST with a PD on (r, ṙ).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState
from rocoma_can.interfaces import Controller, SwapState

from .joint_group import JointGroup
from .params import choice, number, optional_per_joint, output_mode, param_error, per_joint
from .pd_law import PdGains, track
from .pose_swap import PoseSwapState, find_pose_state

KINDS = ("sine", "min_jerk")


def min_jerk(tau: float) -> tuple[float, float]:
    """s(tau) and ds/dtau of the minimum-jerk profile, tau clipped to [0, 1]."""
    if tau <= 0.0:
        return 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0
    t2 = tau * tau
    return t2 * tau * (10.0 - 15.0 * tau + 6.0 * t2), 30.0 * t2 * (1.0 - 2.0 * tau + t2)


class Trajectory(Controller[JointState, JointCommand]):
    """Follows a sine or a minimum-jerk move.

    Parameters (per-joint ones take a scalar or one value per selected joint):
      joints        joint names this controller drives (default: all)
      kind          "sine" (default) or "min_jerk"
      amplitude     sine amplitude, rad, >= 0
      frequency     sine frequency, Hz, >= 0
      offset        sine centre, rad (default: the start pose)
      phase         sine phase, rad
      blend_time    sine: seconds to blend from the start pose into the sine, >= 0
      target        min_jerk: end pose, rad (required for min_jerk)
      duration      min_jerk: seconds, > 0
      mode          "CSP" (default) or "CST"
      kp, kd, torque_limit   the PD used in CST (as for ``pd``)
    """

    def __init__(self, name: str = "trajectory", *, joints: Sequence[str] | None = None,
                 kind: str = "sine", amplitude: object = 0.0, frequency: object = 0.0,
                 offset: object = None, phase: object = 0.0, blend_time: object = 1.0,
                 target: object = None, duration: object = 1.0, mode: object = "CSP",
                 kp: object = 50.0, kd: object = 2.0, torque_limit: object = math.inf) -> None:
        super().__init__(name)
        self.group = JointGroup(self, joints)
        self.kind = choice(self, "kind", kind, KINDS)
        self._p_amplitude = per_joint(self, "amplitude", amplitude, minimum=0.0)
        self._p_frequency = per_joint(self, "frequency", frequency, minimum=0.0)
        self._p_offset = optional_per_joint(self, "offset", offset)
        self._p_phase = per_joint(self, "phase", phase)
        self._p_target = optional_per_joint(self, "target", target)
        if self.kind == "min_jerk":
            if self._p_target is None:
                raise param_error(self, "target", "is required for kind 'min_jerk'")
            self.blend = number(self, "duration", duration, positive=True)
        else:
            if self._p_target is not None:
                raise param_error(self, "target", "is only for kind 'min_jerk' (a sine is "
                                                  "given by amplitude/frequency/offset/phase)")
            self.blend = number(self, "blend_time", blend_time, minimum=0.0)
        self.mode = output_mode(self, mode, (JointMode.CSP, JointMode.CST))
        # in CST the PD runs here on the joint velocity; in CSP the drive's own loop does
        self.feedback_needed = frozenset(
            {"position", "velocity"} if self.mode == JointMode.CST else {"position"})
        self._gains = PdGains.check(self, kp, kd, torque_limit)
        self.time = 0.0

    # --- set-up (not in the cycle) -------------------------------------------------------
    def create(self, dt: float) -> bool:
        g = self.group
        g.bind(self.state, self.command)
        n = g.n
        self.law = self._gains.law(self, n)
        self.amplitude = self._p_amplitude.resolve(self, n)
        self.omega = 2.0 * math.pi * self._p_frequency.resolve(self, n)
        self.phase = self._p_phase.resolve(self, n)
        self._offset_param = None if self._p_offset is None else self._p_offset.resolve(self, n)
        self.offset = np.zeros(n)
        self.target = (np.zeros(n) if self._p_target is None
                       else self._p_target.resolve(self, n))
        self.start = np.zeros(n)
        self.reference = np.zeros(n)
        self.reference_velocity = np.zeros(n)
        self._goal = np.zeros(n)
        self._goal_velocity = np.zeros(n)
        self._angle = np.zeros(n)
        self._scratch = np.zeros(n)
        return True

    def initialize(self, dt: float) -> bool:
        self.group.read()
        self._begin(self.group.q)
        return True

    def swap(self, dt: float, swap_state: SwapState | None) -> bool:
        """Start from the predecessor's reference where it hands one over (bumpless)."""
        self.group.read()
        start = self.group.q.copy()
        pose = find_pose_state(swap_state)
        if pose is not None:
            pose.fill("reference", self.group.names, start)
        self._begin(start)
        return True

    def _begin(self, start: np.ndarray) -> None:
        np.copyto(self.start, start)
        np.copyto(self.offset, start if self._offset_param is None else self._offset_param)
        self.time = 0.0
        self._reference_at(0.0)

    def get_swap_state(self) -> PoseSwapState:
        self.group.read()
        end = self.target if self.kind == "min_jerk" else self.offset
        return PoseSwapState(self.group.names, self.reference.copy(),
                             self.reference_velocity.copy(), end.copy(), self.group.q.copy())

    @property
    def finished(self) -> bool:
        """True once a min_jerk move has arrived (a sine never finishes)."""
        return self.kind == "min_jerk" and self.time >= self.blend

    # --- the cycle ----------------------------------------------------------------------
    def advance(self, dt: float) -> bool:
        self.time += dt
        self._reference_at(self.time)
        g = self.group
        g.read()
        track(g, self.law, self.mode, self.reference, self.reference_velocity, None)
        g.write()
        return True

    def _reference_at(self, t: float) -> None:
        goal, goal_velocity = self._goal, self._goal_velocity
        if self.kind == "sine":
            angle = self._angle
            np.multiply(self.omega, t, out=angle)
            np.add(angle, self.phase, out=angle)
            np.sin(angle, out=goal)
            np.multiply(goal, self.amplitude, out=goal)
            np.add(goal, self.offset, out=goal)
            np.cos(angle, out=goal_velocity)
            np.multiply(goal_velocity, self.amplitude, out=goal_velocity)
            np.multiply(goal_velocity, self.omega, out=goal_velocity)
        else:
            np.copyto(goal, self.target)
            goal_velocity.fill(0.0)
        if self.blend > 0.0:
            s, ds = min_jerk(t / self.blend)
            ds /= self.blend
        else:
            s, ds = 1.0, 0.0
        r, dr, delta = self.reference, self.reference_velocity, self._scratch
        np.subtract(goal, self.start, out=delta)      # g - p0
        np.multiply(delta, s, out=r)
        np.add(r, self.start, out=r)                   # r = p0 + s (g - p0)
        np.multiply(delta, ds, out=dr)
        np.multiply(goal_velocity, s, out=delta)
        np.add(dr, delta, out=dr)                      # ṙ = ṡ (g - p0) + s ġ
