"""What happened, kept: the loop's signals and the bus's frames, written off the loop
(extras ``record``, ``plot``).

trace    the loop's signals every cycle in a ring allocated once; MCAP files written off it
flight   the flight recorder (``run``, on by default) and ``run --record``
can_log  raw CAN frames to candump, ASC or BLF files
plot     one PNG of a trace
"""
