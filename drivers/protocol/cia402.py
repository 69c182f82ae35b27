"""CiA 402 (drive profile) constants shared by the driver and the simulated drive: the drive
objects, the statusword/controlword state machine, modes of operation, 0x6007 options.

One table for both sides, so the simulator cannot drift from what the driver expects.
The communication side (objects 0x1000-0x1FFF, COB-IDs, NMT, EMCY codes) is cia301.py.
"""
from __future__ import annotations

import enum

import numpy as np

# --- object dictionary indices -------------------------------------------------------------
ABORT_CONNECTION_OPTION = 0x6007
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
SHUTDOWN_OPTION = 0x605B
DISABLE_OPERATION_OPTION = 0x605C
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
FOLLOWING_ERROR_WINDOW = 0x6065  # increments (0xFFFFFFFF: off)
FOLLOWING_ERROR_TIMEOUT = 0x6066  # ms
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
SOFTWARE_POSITION_LIMIT = 0x607D  # :1 min, :2 max, increments
MAX_PROFILE_VELOCITY = 0x607F  # increments/s
MAX_MOTOR_SPEED = 0x6080  # rpm of the motor
QUICK_STOP_DECELERATION = 0x6085
TARGET_VELOCITY = 0x60FF
POSITION_ENCODER_RESOLUTION = 0x608F  # :1 increments per :2 motor revolutions
GEAR_RATIO = 0x6091  # :1 motor revolutions per :2 shaft revolutions
VELOCITY_OFFSET = 0x60B1
TORQUE_OFFSET = 0x60B2
PROFILE_VELOCITY = 0x6081
HOMING_METHOD = 0x6098
HOME_OFFSET = 0x607C
INTERPOLATION_DATA = 0x60C1  # :1 the position target in IP
INTERPOLATION_PERIOD = 0x60C2  # :1 value, :2 index (period = value x 10^index s)
SUPPORTED_DRIVE_MODES = 0x6502

DEVICE_TYPE_SERVO = 0x00020192  # CiA 402, servo drive

# --- several axes in one node (CiA 402-2) ---------------------------------------------------
#: Axis n of a multi-axis device has the profile's objects 0x6000-0x67FF at + (n - 1) x this
#: (Roboteq's second channel: controlword 0x6840, supported modes 0x6D02).
AXIS_STRIDE = 0x800
MAX_AXES = 8
_AXIS_OBJECTS = range(0x6000, 0x6000 + AXIS_STRIDE)


def on_axis(index: int, axis: int) -> int:
    """Where axis ``axis`` (1..8) has the profile object ``index`` (objects outside
    0x6000-0x67FF are the node's, shared by its axes)."""
    return index + (axis - 1) * AXIS_STRIDE if index in _AXIS_OBJECTS else index


# --- CiA 402 state machine -----------------------------------------------------------------
class State402(enum.IntEnum):
    UNKNOWN = -1
    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


# (mask, value, state), checked in this order: the 0x4F-masked states first.
STATUSWORD_PATTERNS: tuple[tuple[int, int, State402], ...] = (
    (0x4F, 0x00, State402.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State402.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State402.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State402.SWITCHED_ON),
    (0x6F, 0x27, State402.OPERATION_ENABLED),
    (0x6F, 0x07, State402.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State402.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State402.FAULT),
)

# Statusword value bits per state (what a drive reports; bit 4 voltage enabled and
# bit 5 quick stop are added by the drive on top of these).
STATUSWORD_OF_STATE: dict[State402, int] = {s: v for _, v, s in STATUSWORD_PATTERNS}

SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # active low: 0 = quick stop active
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_FOLLOWING_ERROR = 1 << 13  # CSP/PP: following error (homing: homing error)


def state_from_statusword(statusword: int) -> State402:
    for mask, value, state in STATUSWORD_PATTERNS:
        if statusword & mask == value:
            return state
    return State402.UNKNOWN


def _state_table() -> np.ndarray:
    # Only bits 0-6 decide the state; a table of every 16-bit statusword (64 KiB) decodes a
    # whole array in one take(), without the masked temporary (a quarter of the cost)
    low_bits = np.array([state_from_statusword(sw) for sw in range(128)], dtype=np.int8)
    table: np.ndarray = np.take(low_bits, np.arange(1 << 16) & 0x7F)
    table.setflags(write=False)  # shared by every hardware instance
    return table


STATE_OF_STATUSWORD: np.ndarray = _state_table()


def states_from_statuswords(statuswords: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Vectorised state_from_statusword of uint16 statuswords into a pre-allocated int8
    array."""
    return STATE_OF_STATUSWORD.take(statuswords, out=out)


class Controlword(enum.IntEnum):
    DISABLE_VOLTAGE = 0x0000  # the torque-off command: power stage off, motor coasts
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    DISABLE_OPERATION = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080  # rising edge of bit 7


CW_HALT = 1 << 8


class Mode(enum.IntEnum):
    """Modes of operation (0x6060 / 0x6061)."""
    NONE = 0
    PROFILE_POSITION = 1
    VELOCITY = 2
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CSP = 8
    CSV = 9
    CST = 10


class AbortConnectionOption(enum.IntEnum):
    """0x6007: what the drive does on heartbeat loss, bus-off, NMT stop or reset."""
    NONE = 0
    FAULT = 1
    DISABLE_VOLTAGE = 2
    QUICK_STOP = 3
