"""Live views of a running manager for tools outside the project (extra ``foxglove``):
foxglove.py serves it on a Foxglove WebSocket; messages.py holds its channels (the MCAP
recordings write the same), urdf.py the robot the config names."""
