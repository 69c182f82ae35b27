"""Live views of a running manager for tools outside the project (extra ``foxglove``):
foxglove.py is the loop's process's side of the live view, server.py its Foxglove
WebSocket, served from the recording's writer process behind front.py (the listening
socket: the protocol under both its names); messages.py holds its channels (the MCAP
recordings write the same), urdf.py the robot the config names."""
