"""CANopen master side: bus, CiA 402 drive driver, supervision, and the simulated drive."""
from .cia402 import Controlword, Mode, NmtState, State402
from .joints import JointCommand, JointMode, JointState

__all__ = ["Controlword", "Mode", "NmtState", "State402",
           "JointCommand", "JointMode", "JointState"]
