"""Joint commands from a ROS 2 topic (entry point ``ros2_command``): what ros2_control's
topic-based hardware interface publishes (sensor_msgs/JointState on
``/robot_joint_command``), so JointTrajectoryController, MoveIt and teleop drive the robot
with the emergency and failproof layers underneath (docs/ros2.md).

The ROS 2 node (``run --ros2``) delivers every message to ``take_command`` on its own
thread; the cycle takes the latest (one reference read). The controller fails, and its
emergency controller takes over as from any failing controller, when the latest command
is older than ``timeout``, names a joint it does not drive, holds NaN or a value past its
limits, or has no value for one of its joints in its mode. It commands the joints of the
message it drives; a joint of its group the message leaves out keeps the last command.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from rocoma_can.drivers.protocol.joints import JointCommand, JointMode, JointState
from rocoma_can.inputs import JointCommandSample, topic_problem
from rocoma_can.interfaces import Controller

from .joint_group import JointGroup
from .params import number, output_mode, param_error, per_joint

#: which field of the message each mode commands
_FIELD = {JointMode.CSP: "position", JointMode.CSV: "velocity", JointMode.CST: "effort"}


class Ros2Command(Controller[JointState, JointCommand]):
    """Follows joint commands published on a ROS 2 topic.

    Parameters:
      topic           the command topic (default /robot_joint_command; relative names are
                      in the node's namespace)
      joints          joint names it drives (default: all)
      mode            "CSP" (position, default), "CSV" (velocity) or "CST" (effort)
      rate            Hz the commands come at (default 100): the timeout's unit
      timeout         s a command stays valid (default: 3 periods of ``rate``)
      position_min, position_max   rad, per joint (default: none)
      velocity_limit  |rad/s|, per joint (default: none)
      effort_limit    |Nm|, per joint (default: none)
    """

    def __init__(self, name: str = "ros2_command", *, topic: object = "/robot_joint_command",
                 joints: Sequence[str] | None = None, mode: object = "CSP",
                 rate: object = 100.0, timeout: object = None,
                 position_min: object = -math.inf, position_max: object = math.inf,
                 velocity_limit: object = math.inf, effort_limit: object = math.inf) -> None:
        super().__init__(name)
        problem = topic_problem(topic)
        if problem or not isinstance(topic, str):
            raise param_error(self, "topic", str(problem))
        self._topic = topic
        self.group = JointGroup(self, joints)
        self.mode = output_mode(self, mode, tuple(_FIELD))
        self.rate = number(self, "rate", rate, positive=True)
        self.timeout = (3.0 / self.rate if timeout is None
                        else number(self, "timeout", timeout, positive=True))
        self._p_min = per_joint(self, "position_min", position_min, allow_inf=True)
        self._p_max = per_joint(self, "position_max", position_max, allow_inf=True)
        self._p_velocity = per_joint(self, "velocity_limit", velocity_limit, positive=True,
                                     allow_inf=True)
        self._p_effort = per_joint(self, "effort_limit", effort_limit, positive=True,
                                   allow_inf=True)
        self.feedback_needed = frozenset({"position"})
        self._latest: JointCommandSample | None = None
        self._applied: JointCommandSample | None = None

    @property
    def command_topic(self) -> str:
        return self._topic

    def take_command(self, sample: JointCommandSample) -> None:
        """Any thread (the ROS 2 node's): the latest command, one assignment."""
        self._latest = sample

    # --- set-up (not in the cycle) -------------------------------------------------------
    def create(self, dt: float) -> bool:
        g = self.group
        g.bind(self.state, self.command)
        n = g.n
        self._slot = {name: i for i, name in enumerate(g.names)}
        low = self._p_min.resolve(self, n)
        high = self._p_max.resolve(self, n)
        if self.mode == JointMode.CSP:
            self._low, self._high = low, high
        else:
            bound = (self._p_velocity if self.mode == JointMode.CSV
                     else self._p_effort).resolve(self, n)
            self._low, self._high = -bound, bound
        self._values = np.zeros(n)
        self._target = {JointMode.CSP: g.position, JointMode.CSV: g.velocity,
                        JointMode.CST: g.torque}[self.mode]
        return True

    def initialize(self, dt: float) -> bool:
        """Starts from the measured pose (CSP) or zero (CSV, CST) until the first command;
        the timeout counts from now, so a topic nobody publishes fails it then."""
        g = self.group
        g.read()
        g.set_mode(self.mode)
        np.copyto(self._values, g.q if self.mode == JointMode.CSP else 0.0)
        self._applied = None
        self._since = time.monotonic()
        return True

    # --- the cycle ----------------------------------------------------------------------
    def advance(self, dt: float) -> bool:
        sample = self._latest
        now = time.monotonic()
        if sample is not None and sample.received < self._since:
            sample = None  # from before this activation: not a command to follow
        fresh_from = sample.received if sample is not None else self._since
        if now - fresh_from > self.timeout:
            raise TimeoutError(f"no command on {self._topic} for {now - fresh_from:.3f} s "
                               f"(timeout {self.timeout:g} s)")
        if sample is not None and sample is not self._applied:
            self._apply(sample)
            self._applied = sample
        np.copyto(self._target, self._values)
        self.group.write()
        return True

    def _apply(self, sample: JointCommandSample) -> None:
        """A new command into ``_values``; ValueError says what makes it unusable. Reads at
        most one name past the joints it drives (the sample's own check was made where it
        arrived: no name twice, so every name read before an unknown one is a joint of
        ours)."""
        if sample.problem:
            raise ValueError(f"command on {self._topic}: {sample.problem}")
        field = _FIELD[self.mode]
        values = getattr(sample, field)
        if not values:
            raise ValueError(f"command on {self._topic} has no {field} (mode "
                             f"{self.mode.name})")
        for name, value in zip(sample.names, values):
            i = self._slot.get(name)
            if i is None:
                raise ValueError(f"command on {self._topic} names joint {name!r}, which "
                                 f"{self.name} does not drive ({', '.join(self.group.names)})")
            if not self._low[i] <= value <= self._high[i]:  # (NaN fails both)
                raise ValueError(f"command on {self._topic}: {field} {value} for {name} "
                                 f"outside {self._low[i]:g}..{self._high[i]:g}")
            self._values[i] = value
