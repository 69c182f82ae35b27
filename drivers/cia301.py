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
HEARTBEAT = 0x700


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
