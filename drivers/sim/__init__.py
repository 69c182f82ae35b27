"""Simulated CiA 402 drives on a CAN bus, for bench tests without hardware.

``segment`` is the bus side (one socket, the receive and timer threads; its options in
``segment_options``, its nodes and their routes in ``nodes_on_bus``), ``group`` several
segments on one receive thread (or in lockstep, for the demo), and ``port`` what a drive
sees of it; ``drive`` composes one drive (one CANopen node of one or more CiA 402 axes)
from one module per CANopen service: ``objects`` (object dictionary, SDO server), ``nmt``
(NMT, heartbeats), ``pdo``, ``axis`` (one CiA 402 axis) with its ``state_machine``
(CiA 402, loops), ``limits`` (the drive-side limit objects honoured), ``faults`` (EMCY,
injected faults), ``lss`` (the LSS slave, CiA 305); ``dynamics`` holds the joints (one per
axis), ``timers`` the segment's timer thread, and ``cli`` is ``rocoma-can sim``.
"""
