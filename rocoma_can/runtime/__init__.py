"""What runs the manager on a bus: its config, the loop, the system wired from them, and what
``doctor`` judges of the host.

The loop's order (run_cycle) is written in one place, loop.py. The modules: the module map in
docs/architecture.md (tools/module-map writes it from their docstrings). Public names are imported
on first use (``_lazy.py``)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

__all__ = ["ControlLoop", "CycleStats", "TimingSummary", "run_cycle", "set_realtime",
           "Runtime", "manager_for"]
__getattr__, __dir__ = lazy_exports(__name__, {
    "ControlLoop": "loop", "CycleStats": "loop", "TimingSummary": "loop",
    "run_cycle": "loop", "set_realtime": "loop", "Runtime": "system", "manager_for": "system",
})

if TYPE_CHECKING:
    from .loop import ControlLoop, CycleStats, TimingSummary, run_cycle, set_realtime
    from .system import Runtime, manager_for
