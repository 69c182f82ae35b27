"""Managers on Zenoh (extra ``zenoh``): one manager per robot, coordinated over the network; the
control loop never goes over it.

The bridge serves the manager's services and notifications, the client talks to managers (the CLI
verbs' ``--zenoh`` and ``rocoma-can fleet``). The modules: the module map in docs/architecture.md
(tools/module-map writes it from their docstrings).
"""
