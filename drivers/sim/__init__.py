"""Simulated CiA 402 drives on a CAN bus, for bench tests without hardware.

``segment`` is the bus side (one socket, the receive and timer threads, routing), ``group``
several segments on one receive thread (or in lockstep, for the demo), and
``port`` what a drive sees of it; ``drive`` composes one drive (one CANopen node of one or
more CiA 402 axes) from one module per CANopen service: ``objects`` (object dictionary, SDO
server), ``nmt`` (NMT, heartbeats), ``pdo``, ``state_machine`` (CiA 402, loops; one per
axis), ``limits`` (the drive-side limit objects honoured), ``faults`` (EMCY, injected
faults), ``lss`` (the LSS slave, CiA 305); ``dynamics`` holds the joints (one per axis),
``timers`` the segment's timer thread, and ``cli`` is ``rocoma-can sim``.
"""
