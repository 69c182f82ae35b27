"""The protocol stage: CANopen and CiA 402 as codecs and constants, no I/O and no state.

Everything above it (the plan, the link, the cycle, the simulated drive) speaks in these terms:
the CiA 301 and CiA 402 constants, what a frame costs on the wire, the joint state and command
the controllers read and write, and the SDO block upload server both the manager's node and
the simulated drive serve their text objects with."""
