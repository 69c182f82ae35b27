"""The manager's own CANopen node (eds/rocoma_manager.eds): how other nodes and the CLI
switch controllers, e-stop, clear and read the manager's state over the bus.

server      the node: SDO services, the e-stop frame, state and EMCY frames (ManagerNode)
sdo_server  canopen's SDO server made strict (a transfer that must not take effect never does)
objects     the node's objects, values and abort codes, shared by server and client
client      ManagerClient: what the CLI verbs (and any program) use to talk to a node
sdo_block   SDO block upload, the client's side
sdo_write   an expedited SDO download that takes only its own answer
"""
