"""What happened, kept: the loop's signals and the bus's frames, written off the loop
(extras ``record``, ``plot``).

trace          the loop's signals every cycle in a ring allocated once; MCAP writing, reading
mcap_file      MCAP files written in bulk: a message is one pack and two appends
rings          rings in shared memory: what the loop's process hands the writer process
recorder       the loop's side of recording: the rings, the writer process, its replies
writer         the writer process (``python -m rocoma_can.record.writer``), which also
               serves the Foxglove live view (live/server.py)
pacing         the writer process yields its CPU every 0.2 ms of work: a loop queued on its
               CPU waits for one piece, not a writing burst
recording      ``run --record``'s files, in the writer process
flight         the flight recorder (``run``, on by default), in the writer process
live_channels  the live view's channels in the recordings
can_log        raw CAN frames to candump, ASC or BLF files
plot     one PNG of a trace
"""
