"""Live views of a running manager for tools outside the project (extra ``foxglove``).

The loop's process feeds the view (foxglove.py); its Foxglove WebSocket is served from the
recording's writer process, off the rows it reads, so building and sending messages never takes the
loop's interpreter lock; the recordings carry the same channels. The modules: the module map in
docs/architecture.md (tools/module-map writes it from their docstrings)."""
