"""The manager as a ROS 2 node over rmw_zenoh, with no ROS install (extra ``ros2``; docs/ros2.md).

The modules: the module map in docs/architecture.md (tools/module-map writes it from their
docstrings).
"""
