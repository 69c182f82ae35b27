"""Managers on Zenoh (extra ``zenoh``): one manager per robot, coordinated over the network;
the control loop never goes over it.

bridge  the manager's services and notifications on Zenoh (FleetBridge)
config  the ``zenoh:`` config section (FleetConfig, parse_fleet)
client  talking to managers over Zenoh: the CLI verbs' ``--zenoh`` and ``rocoma-can fleet``
"""
