"""rocoma-can: the rocoma controller manager for CANopen actuator buses."""
from .interfaces import Controller, EmergencyController, FailproofController, SwapState

__all__ = ["Controller", "EmergencyController", "FailproofController", "SwapState"]
