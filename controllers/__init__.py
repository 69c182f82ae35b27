"""Controller plugins: failproof torque-off, emergency controllers, PD, trajectories.

torque_off (the failproof layer); emergency controllers damp, hold, quick_stop, float
(zero torque); controllers pd, trajectory, tracking_monitor (a worker example), ros2_command
(joint commands from a ROS 2 topic); what they
share: pd_law (the PD law and tracking step), joint_group (the joints one controller
drives), params (parameter checks), pose_swap (the pose handed over on a switch)."""
from __future__ import annotations

from importlib import resources
from pathlib import Path


def example_path(name: str = "tuple.yaml") -> Path:
    """A controller configuration shipped in controllers/examples/ (package data)."""
    path = Path(str(resources.files(__name__).joinpath("examples").joinpath(name)))
    if not path.is_file():
        raise FileNotFoundError(f"no example controller configuration {name!r} in {path.parent}")
    return path
