"""CANopen master side: bus, CiA 402 drive driver, supervision, and the simulated drive.

The hardware layer, one module per job (the safety path is told in hardware's docstring):
hardware (CanopenHardware: wires the others; read and write), receive (every received frame
by COB-ID into JointState), supervision (every symptom -> one FaultEvent), stop_requests
(what read returns for the manager), command (JointCommand -> controlword, mode, targets),
frames_out (every frame sent, torque-off first), node_guarding, recovery, status, homing,
enable (the CiA 402 enable sequence), switch_off (controlword 0 by SDO to a latched drive).
Start-up: bringup (per-drive state machine and SDO configuration), drive_plan (a config
measured against its EDS/DCF), identity (0x1018: the drive bring-up requires), limits
(drive-side joint limits written and read back), capabilities (what the file offers),
device_file (the tolerant EDS/DCF reader), pdo_layout, modes, scaling, joints
(JointState, JointCommand), config (DriveConfig, BusConfig). CANopen and the wire: cia301,
cia402, bus (python-can bus, canopen Network, reader threads), bus_port (one bus of the
hardware), frame_io, inproc (the in-process bus), inproc_link (joins two processes'
inproc channels), sdo_block_upload (server side), wire
(frame bits).
First contact: scan (every node on a bus, by SDO reads only), lss (CiA 305: node ids for
nodes without one), can_link (a SocketCAN link as sysfs and iproute2 report it).
sim/ is the simulated drive.

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
