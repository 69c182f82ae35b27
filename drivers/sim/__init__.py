"""Simulated CiA 402 drives on a CAN bus, for bench tests without hardware.

``segment`` is the bus side (one socket, the receive and timer threads, routing), ``group``
several segments on one receive thread (or in lockstep, for the demo), and
``port`` what a drive sees of it; ``drive`` composes one drive (one CANopen node of one or
more CiA 402 axes) from one module per CANopen service: ``objects`` (object dictionary, SDO
server), ``nmt`` (NMT, heartbeats), ``pdo``, ``state_machine`` (CiA 402, loops; one per
axis), ``faults`` (EMCY, injected faults); ``dynamics`` holds the joints (one per axis) and
``cli`` is ``rocoma-can sim``.
"""
