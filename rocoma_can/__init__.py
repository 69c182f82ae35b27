"""rocoma-can: the rocoma controller manager for CANopen actuator buses.

The core (this folder's modules) is the manager, its switcher and stopper threads and the controller
interfaces; the folders around it run it on a bus (runtime), make it a CANopen node (node), keep
what happened (record), show it to outside tools (live, ros2, fleet) and make the ``rocoma-can``
command (cli); drivers and controllers are installed into this namespace. Every module, with what it
holds: the module map in docs/architecture.md (tools/module-map writes it from their docstrings).

The public names are imported on first use (``_lazy.py`` says why).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from ._lazy import lazy_exports

__version__ = "0.3.0"  # the distribution's version (pyproject.toml reads it from here)

__all__ = [
    "ControllerManager", "ManagerState", "ManagerTimeouts", "SwitchResult", "TimingSupervision",
    "EventKind", "ManagerEvent",
    "Controller", "EmergencyController", "FailproofController", "SwapState",
    "ControllerTuple", "EmergencyControllerTuple", "TupleSwapState",
    "WorkerEvent", "WorkerHandle", "WorkerManager", "WorkerOptions",
    "PluginError", "add_to_manager", "create_controller", "load_config",
]
_MODULE_OF = {
    "ControllerManager": "manager", "ManagerTimeouts": "manager_timing",
    "SwitchResult": "manager", "TimingSupervision": "manager_timing",
    "EventKind": "events", "ManagerEvent": "events", "ManagerState": "events",
    "Controller": "interfaces", "EmergencyController": "interfaces",
    "FailproofController": "interfaces", "SwapState": "interfaces",
    "ControllerTuple": "tuples", "EmergencyControllerTuple": "tuples",
    "TupleSwapState": "tuples",
    "WorkerEvent": "workers", "WorkerHandle": "workers", "WorkerManager": "workers",
    "WorkerOptions": "workers",
    "PluginError": "errors", "add_to_manager": "plugins", "create_controller": "plugins",
    "load_config": "plugins",
}
__getattr__, __dir__ = lazy_exports(__name__, _MODULE_OF)

if TYPE_CHECKING:
    from .errors import PluginError
    from .events import EventKind, ManagerEvent, ManagerState
    from .interfaces import Controller, EmergencyController, FailproofController, SwapState
    from .manager import ControllerManager, SwitchResult
    from .manager_timing import ManagerTimeouts, TimingSupervision
    from .plugins import add_to_manager, create_controller, load_config
    from .tuples import ControllerTuple, EmergencyControllerTuple, TupleSwapState
    from .workers import WorkerEvent, WorkerHandle, WorkerManager, WorkerOptions
