"""CANopen master side: bus, CiA 402 drive driver, supervision, and the simulated drive.

Public names are imported on first use (rocoma_can/_lazy.py): importing one module of this
package (the bus reader, say) must not import numpy."""
from __future__ import annotations

from typing import TYPE_CHECKING

from rocoma_can._lazy import lazy_exports

__all__ = ["Controlword", "Mode", "NmtState", "State402",
           "JointCommand", "JointMode", "JointState"]
__getattr__, __dir__ = lazy_exports(__name__, {
    "Controlword": "cia402", "Mode": "cia402", "NmtState": "cia301", "State402": "cia402",
    "JointCommand": "joints", "JointMode": "joints", "JointState": "joints",
})

if TYPE_CHECKING:
    from .cia301 import NmtState
    from .cia402 import Controlword, Mode, State402
    from .joints import JointCommand, JointMode, JointState
