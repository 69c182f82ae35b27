"""The manager's own CANopen node (eds/rocoma_manager.eds): how other nodes and the CLI switch
controllers, e-stop, clear and read the manager's state over the bus.

The server and the client share one table of the node's objects (objects.py). The modules: the
module map in docs/architecture.md (tools/module-map writes it from their docstrings).
"""
