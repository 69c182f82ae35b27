"""CiA 301 (the CANopen application layer) constants shared by the driver, the simulated
drive and the manager's node: communication objects, COB-IDs, NMT, EMCY error codes. SDO
abort codes are canopen's (canopen.sdo.constants), not a table of our own.

The drive profile (CiA 402: statusword, controlword, modes) is cia402.py.
"""
from __future__ import annotations

import enum

# --- communication objects -----------------------------------------------------------------
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
PREDEFINED_ERROR_FIELD = 0x1003
GUARD_TIME = 0x100C         # node guarding: the master's guard request period (ms)
LIFE_TIME_FACTOR = 0x100D   # life time = guard time x this factor (the drive's deadline)
CONSUMER_HEARTBEAT_TIME = 0x1016
PRODUCER_HEARTBEAT_TIME = 0x1017
IDENTITY = 0x1018
ERROR_BEHAVIOR = 0x1029
RPDO_COMM = 0x1400  # + n-1
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00

# --- CiA 301 function codes (COB-ID = base + node id) ---------------------------------------
NMT = 0x000
SYNC = 0x080
EMCY = 0x080
TPDO_BASE = (0x180, 0x280, 0x380, 0x480)
RPDO_BASE = (0x200, 0x300, 0x400, 0x500)
SDO_TX = 0x580
SDO_RX = 0x600
HEARTBEAT = 0x700          # heartbeat, boot-up and node guarding (remote request + answer)
#: Node guarding answer: bit 7 toggles with every answer, bits 0..6 are the NMT state.
GUARD_TOGGLE = 0x80

#: An object's place in an object dictionary: (index, subindex)
ObjectKey = tuple[int, int]


def is_cob_id(value: object) -> bool:
    """An 11-bit COB-ID: a whole number 0..0x7FF (a bool is no number here)."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 0x7FF


def reserved_cob_id(cob_id: int) -> str | None:
    """Why an 11-bit COB-ID cannot be a free-standing identifier such as the e-stop frame's
    (NMT, SYNC, SDO and heartbeat ranges), or None. PDO and EMCY ids depend on the nodes on
    the bus: ``used_cob_ids`` gives those."""
    if cob_id in (NMT, SYNC) or SDO_TX <= cob_id <= SDO_RX + 0x7F or cob_id >= HEARTBEAT:
        return "reserved for NMT, SYNC, SDO or heartbeat frames"
    return None


def node_cob_ids(node_id: int) -> dict[int, str]:
    """The predefined connection set of one node: its EMCY and PDO COB-IDs, named."""
    ids = {EMCY + node_id: f"the EMCY of node {node_id}"}
    for k, base in enumerate(TPDO_BASE):
        ids[base + node_id] = f"TPDO{k + 1} of node {node_id}"
    for k, base in enumerate(RPDO_BASE):
        ids[base + node_id] = f"RPDO{k + 1} of node {node_id}"
    return ids


class NmtCommand(enum.IntEnum):
    START = 0x01
    STOP = 0x02
    PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(enum.IntEnum):
    """Heartbeat payload byte."""
    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def nmt_name(state: int) -> str:
    """An NMT state (a heartbeat's byte) as CiA 301 spells it and every output of
    rocoma-can shows it (status, scan, supervision's faults, the simulator's lines):
    OPERATIONAL, PRE-OPERATIONAL, STOPPED, BOOT-UP; 0xNN for any other value."""
    try:
        return NmtState(state).name.replace("_", "-")
    except ValueError:
        return f"0x{state:02X}"


# EMCY error codes used by the simulator and understood by the driver.
EMCY_NO_ERROR = 0x0000
EMCY_GENERIC = 0x1000
EMCY_OVERCURRENT = 0x2310
EMCY_OVERVOLTAGE = 0x3210
EMCY_OVERTEMPERATURE = 0x4310
EMCY_HEARTBEAT = 0x8130  # life guard / heartbeat error
EMCY_POSITION_SENSOR = 0x7305
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_PDO_LENGTH = 0x8210  # RPDO not processed: shorter than its mapping
EMCY_STO = 0x5441  # vendor area commonly used for "STO input active"
