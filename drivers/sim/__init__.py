"""Simulated CiA 402 drives on a CAN bus, for bench tests without hardware: ``segment`` (the
bus side: one socket, the receive and timer threads, routing), ``drive`` (one drive: its
object dictionary, NMT, SDO server, PDOs, CiA 402 state machine, faults), ``dynamics`` (the
joints), ``cli`` (``rocoma-can sim``)."""
