"""The protocol stage: CANopen and CiA 402 as codecs and constants, no bus of its own.

Everything above it (the plan, the link, the cycle, the simulated drive) speaks in these terms:
the CiA 301 and CiA 402 constants, what a frame costs on the wire, the joint state and command
the controllers read and write. One piece keeps state: the SDO block upload server (a
protocol's state machine, not a bus's), which the manager's node and the simulated drive both
serve their text objects with through canopen's SdoServer."""
