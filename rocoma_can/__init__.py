"""rocoma-can: the rocoma controller manager for CANopen actuator buses."""
from .events import EventKind, ManagerEvent, ManagerState
from .interfaces import Controller, EmergencyController, FailproofController, SwapState
from .manager import ControllerManager, ManagerTimeouts, SwitchResult
from .tuples import ControllerTuple, TupleSwapState
from .workers import WorkerEvent, WorkerOptions

__all__ = [
    "ControllerManager", "ManagerState", "ManagerTimeouts", "SwitchResult",
    "EventKind", "ManagerEvent",
    "Controller", "EmergencyController", "FailproofController", "SwapState",
    "ControllerTuple", "TupleSwapState", "WorkerEvent", "WorkerOptions",
]
