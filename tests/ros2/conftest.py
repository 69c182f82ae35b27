"""Fixtures of the ROS 2 node's tests (the rig: tests/fixtures/ros2_rig.py)."""
from __future__ import annotations

from fixtures.ros2_rig import peer, ros2_sdk, router

__all__ = ["peer", "ros2_sdk", "router"]
