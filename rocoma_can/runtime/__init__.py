"""What runs the manager on a bus: config (the YAML, checked whole), config_check (its
checks of the sections that stand alone), config_drives (the checks that need the drives),
bus_load (what the config puts on each bus), loop (run_cycle, the
cycle's order in one place; one thread, fixed rate, a safe way out), system (hardware,
manager, node, recorders and fleet bridge wired), host and can_checks (what ``doctor``
judges: the host for a 1 kHz loop, each CAN link against its bus), host_timing (``doctor
--timing``: the bare loop measured, does this host keep a loop's speed). Public names are
imported on first use (``_lazy.py``)."""
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
