"""The manager as a ROS 2 node over rmw_zenoh, with no ROS install (extra ``ros2``;
docs/ros2.md).

interfaces  the types served, their RIHS01 hashes and CDR codec (rosbags), per distro
graph       key expressions, liveliness tokens, QoS text and attachments (rmw_zenoh's
            docs/design.md)
messages    the messages published and answered, from plain values
node        Ros2Node: the publications, the services, the command subscriptions
config      the ``ros2:`` section and the ``--ros2`` options
"""
