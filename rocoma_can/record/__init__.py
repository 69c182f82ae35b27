"""What happened, kept: the loop's signals and the bus's frames, written off the loop (extras
``record``, ``plot``).

The loop's process hands rows and frames over in shared-memory rings; a writer process of its own
writes the flight records, ``run --record``'s files and serves the Foxglove live view. The modules:
the module map in docs/architecture.md (tools/module-map writes it from their docstrings).
"""
