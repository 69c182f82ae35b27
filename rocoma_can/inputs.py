"""Commands from outside the manager for the controllers that follow them: a controller
that takes joint commands from a topic (controllers/ros2_command.py) says which
(``command_topic``) and takes each sample (``take_command``, called from the transport's
thread, never the cycle's); the ROS 2 node (rocoma_can/ros2/) delivers them. The
controllers see only this seam, not the transport."""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

#: a ROS 2 name token: a letter or '_' first, then letters, digits, '_'
NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def topic_problem(topic: object) -> str | None:
    """Why ``topic`` is no ROS 2 topic name, absolute (``/a/b``) or relative to the node's
    namespace (``a/b``); None: it is one. Its chunks are name tokens: a wildcard would
    follow every JointState it matches, the robot's own joint states among them."""
    if isinstance(topic, str):
        chunks = topic.removeprefix("/").split("/")
        if all(NAME_TOKEN.fullmatch(chunk) for chunk in chunks):
            return None
    return f"expected a topic name such as /robot_joint_command, got {topic!r}"


@dataclass(frozen=True)
class JointCommandSample:
    """One joint command as it arrived (a sensor_msgs/JointState: names, and per name a
    position, velocity and effort, any of the three lists empty when not commanded);
    ``received``: time.monotonic() on arrival. ``problem``: what makes it unusable ("" when
    nothing does: a list neither empty nor as long as the names, a name twice), found
    where the sample is made, on the transport's thread: a message may hold any number of
    names, and the cycle must not pay for reading them all."""
    names: tuple[str, ...]
    position: tuple[float, ...]
    velocity: tuple[float, ...]
    effort: tuple[float, ...]
    received: float
    problem: str = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "problem", self._find_problem())

    def _find_problem(self) -> str:
        n = len(self.names)
        for name, values in (("position", self.position), ("velocity", self.velocity),
                             ("effort", self.effort)):
            if values and len(values) != n:
                return f"{len(values)} {name} values for {n} joints"
        if len(set(self.names)) != n:
            return "a joint named twice"
        return ""


@runtime_checkable
class TopicCommanded(Protocol):
    """A controller that follows joint commands published on ``command_topic``."""

    @property
    def command_topic(self) -> str: ...

    def take_command(self, sample: JointCommandSample) -> None: ...
