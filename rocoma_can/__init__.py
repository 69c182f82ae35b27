"""rocoma-can: the rocoma controller manager for CANopen actuator buses.

The public names are imported on first use (``_lazy.py`` says why). The core's modules:

manager      ControllerManager: states, layers, update() and its e-stops (the safety path)
manager_timing  ManagerTimeouts and TimingSupervision: how long the manager waits, how long
             its controllers may take
controller_set  the controllers a manager holds, by name, each with its emergency controller
switcher     the switch protocol, on the manager's switcher thread (Switcher, SwitchResult)
stopper      the manager's stopper threads and its hang watchdog
adapters     how the manager calls a controller: judged results, timing budgets
interfaces   Controller, EmergencyController, FailproofController, SwapState
tuples       controller tuples (several controllers as one)
workers      worker threads owned by a controller
events       notifications and logging, delivered off the cycle
plugins      controllers by name from configuration (entry points)
overrun      when a control cycle overran: one rule for statistics, recordings, view
remote       the rules for commands from afar (Zenoh, Foxglove, ROS 2): stops always, the
             rest when allowed
inputs       commands from outside for the controllers that follow a topic (ros2_command)
errors       RocomaError, the one root of the errors raised on purpose
user_files   files a user names (URDF, EDS) read only when regular: a FIFO cannot hang
cli_args     argument types every verb shares
exit_codes   the exit codes every verb shares
__main__     ``python -m rocoma_can``: the rocoma-can command
_lazy        package attributes imported on first use (a fast CLI start)

Subpackages: runtime (the manager on a bus), node (its CANopen node), record, fleet, live
(the Foxglove view), ros2 (a ROS 2 node over rmw_zenoh), cli;
drivers and controllers are installed into this namespace.
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
