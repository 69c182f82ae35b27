"""The ``rocoma-can`` command: the parser (main) and the verbs, each verb's module registering
itself.

``rocoma-can fleet`` lives with the fleet (fleet/client.py), ``rocoma-can sim`` with the simulator
(drivers/sim/cli.py). The modules: the module map in docs/architecture.md (tools/module-map writes
it from their docstrings).
"""
from __future__ import annotations

from .main import main

__all__ = ["main"]
