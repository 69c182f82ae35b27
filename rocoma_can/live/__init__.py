"""Live views of a running manager for tools outside the project (extra ``foxglove``):
foxglove.py serves it on a Foxglove WebSocket."""
