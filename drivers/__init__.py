"""CANopen master side: the CiA 402 drive driver, a folder per stage, and the simulated drive.

A frame's way through the stages, bottom to top (each imports only the ones before it; the
import contract test holds the order):

- protocol/: CiA 301/402 codecs and constants, the joint types, frame bits; no I/O.
- files/: the tolerant EDS/DCF reader, a drive's capabilities, its identity (0x1018).
- plan/: DriveConfig/BusConfig, a config measured against its file (drive_plan), PDO
  layouts, modes, scaling, drive-side limits.
- link/: python-can buses and their reader threads, one bus of the hardware (bus_port),
  frame I/O, the in-process bus and its link between processes, SocketCAN links.
- bringup/: the per-drive start-up state machine, its SDO configuration, the start-up of
  every drive and its report.
- cycle/: what runs on the loop's thread each cycle (receive, supervision, command,
  frames_out = torque-off, ...) and what it drives off the cycle (recovery, switch_off).
- commission/: scan and LSS, the first look at a robot's bus.
- hardware.py wires the stages into CanopenHardware; its docstring tells the safety path.
- sim/ is the simulated drive, one module per CANopen service.

Public names are imported on first use (rocoma_can/_lazy.py): importing one module of this
package (the bus reader, say) must not import numpy."""
from __future__ import annotations

from typing import TYPE_CHECKING

from rocoma_can._lazy import lazy_exports

__all__ = ["Controlword", "Mode", "NmtState", "State402",
           "JointCommand", "JointMode", "JointState"]
__getattr__, __dir__ = lazy_exports(__name__, {
    "Controlword": "protocol.cia402", "Mode": "protocol.cia402", "NmtState": "protocol.cia301",
    "State402": "protocol.cia402", "JointCommand": "protocol.joints",
    "JointMode": "protocol.joints", "JointState": "protocol.joints",
})

if TYPE_CHECKING:
    from .protocol.cia301 import NmtState
    from .protocol.cia402 import Controlword, Mode, State402
    from .protocol.joints import JointCommand, JointMode, JointState
