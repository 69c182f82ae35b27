"""rocoma-can: the rocoma controller manager for CANopen actuator buses."""
from .events import EventKind, ManagerEvent, ManagerState
from .interfaces import Controller, EmergencyController, FailproofController, SwapState
from .manager import ControllerManager, ManagerTimeouts, SwitchResult, TimingSupervision
from .plugins import PluginError, add_to_manager, create_controller, load_config
from .tuples import ControllerTuple, EmergencyControllerTuple, TupleSwapState
from .workers import WorkerEvent, WorkerHandle, WorkerManager, WorkerOptions

__all__ = [
    "ControllerManager", "ManagerState", "ManagerTimeouts", "SwitchResult", "TimingSupervision",
    "EventKind", "ManagerEvent",
    "Controller", "EmergencyController", "FailproofController", "SwapState",
    "ControllerTuple", "EmergencyControllerTuple", "TupleSwapState",
    "WorkerEvent", "WorkerHandle", "WorkerManager", "WorkerOptions",
    "PluginError", "add_to_manager", "create_controller", "load_config",
]
