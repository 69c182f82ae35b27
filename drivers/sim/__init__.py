"""Simulated CiA 402 drives on a CAN bus, for bench tests without hardware.

``segment`` is the bus side (one socket, the receive and timer threads, routing) and
``port`` what a drive sees of it; ``drive`` composes one drive from one module per CANopen
service: ``objects`` (object dictionary, SDO server), ``nmt`` (NMT, heartbeats), ``pdo``,
``state_machine`` (CiA 402, loops), ``faults`` (EMCY, injected faults); ``dynamics`` holds
the joints and ``cli`` is ``rocoma-can sim``.
"""
