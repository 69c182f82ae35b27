"""The manager node's objects (eds/rocoma_manager.eds), values and SDO abort codes: what the
node (server.py) serves and the client (client.py) asks for, in one place."""
from __future__ import annotations

from canopen.sdo.constants import (
    ABORT_APPLICATION_DEVICE_STATE,
    ABORT_APPLICATION_LOCAL_CONTROL,
    ABORT_CRC_ERROR,
    ABORT_INVALID_BLOCK_SIZE,
    ABORT_INVALID_COMMAND_SPECIFIER,
    ABORT_INVALID_SEQUENCE_NUMBER,
    ABORT_INVALID_VALUE,
    ABORT_LENGTH_TOO_HIGH,
    ABORT_NOT_IN_OD,
    ABORT_TIMED_OUT,
)

SWITCH_NAME, SWITCH_INDEX, SWITCH_RESULT, SWITCH_REFUSAL = 0x2100, 0x2101, 0x2102, 0x2103
DRIVE_STATUS = 0x2140
HOME_DRIVE, HOMING_REFUSAL = 0x2150, 0x2151
ESTOP, FAILPROOF_STOP, CLEAR, RECOVER = 0x2110, 0x2111, 0x2112, 0x2113
STATE, ACTIVE_NAME, ACTIVE_INDEX, CONTROLLER_LIST, ESTOP_CAUSE = (
    0x2120, 0x2121, 0x2122, 0x2123, 0x2124)
ESTOP_COB_ID, ESTOP_LATCHED = 0x2130, 0x2131
PENDING, NO_SWITCH_YET = 0xFF, 0xFE
#: Segments per SDO block the client (sdo_block.upload) asks for: one burst of the node's
#: (sdo_server.BURST), so each block is one round trip without a pause. The node serves any
#: block size 1..127, as stock clients ask.
MAX_BLOCK_SIZE = 8
SEGMENT = 7  # bytes of data in one SDO segment (the frame's first byte is the command)
#: The longest value the node takes by SDO download (a controller or joint name): a longer
#: one is aborted 0x06070012 as it comes, never buffered (a sender could stream segments
#: for ever) nor echoed back in a refusal.
MAX_DOWNLOAD = 256
# SDO abort codes the node answers with (CiA 301; canopen's names)
ABORT_NOT_FOUND = ABORT_INVALID_VALUE  # 0x06090030 value range exceeded: no such controller
ABORT_NO_OBJECT = ABORT_NOT_IN_OD  # 0x06020000 no such object: the node is no manager
ABORT_COMMAND_SPECIFIER = ABORT_INVALID_COMMAND_SPECIFIER  # 0x05040001
ABORT_BLOCK_SIZE = ABORT_INVALID_BLOCK_SIZE  # 0x05040002 blksize outside 1..127
ABORT_SEQUENCE_NUMBER = ABORT_INVALID_SEQUENCE_NUMBER  # 0x05040003 acked more than was sent
ABORT_CRC = ABORT_CRC_ERROR  # 0x05040004 a block upload's data does not match its CRC
ABORT_NO_ANSWER = ABORT_TIMED_OUT  # 0x05040000 SDO protocol timed out
#: 0x0504xxxx: the SDO protocol itself failed (timeout, command, block size, sequence, CRC);
#: the transfer is broken, not refused, and may be started again
PROTOCOL_ABORTS = range(ABORT_NO_ANSWER, ABORT_NO_ANSWER + 0x10000)
ABORT_REFUSED = ABORT_APPLICATION_DEVICE_STATE  # 0x08000022 not in the present device state
ABORT_NO_RECOVERY = ABORT_APPLICATION_LOCAL_CONTROL  # 0x08000021 no drives to recover
ABORT_TOO_LONG = ABORT_LENGTH_TOO_HIGH  # 0x06070012 longer than MAX_DOWNLOAD

RESULT_NAMES = {0: "SWITCHED", 1: "RUNNING", 2: "NOT_FOUND", 3: "ERROR", PENDING: "PENDING",
                NO_SWITCH_YET: "none"}
STATE_NAMES = {0: "FAILPROOF", 1: "EMERGENCY", 2: "OK"}

#: what an abort of the manager node means, for messages (errors.Refused)
ABORT_TEXT = {
    ABORT_NOT_FOUND: "no such controller",
    ABORT_REFUSED: "refused in the present state (e-stop latched, drives not ready, or a "
                   "switch running: 0x2103 says which)",
    ABORT_NO_RECOVERY: "this manager has no drives to recover",
}
