"""Simulated CiA 402 drives on a CAN bus, for bench tests without hardware.

A segment is the bus side (one socket, the receive and timer threads, routing), a group serves
several segments on one receive thread (or in lockstep, for the demo); a drive is composed of one
module per CANopen service. The modules: the module map in docs/architecture.md (tools/module-map
writes it from their docstrings).
"""
