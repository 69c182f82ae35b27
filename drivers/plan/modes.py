"""How each drive carries what a controller commands.

Controllers command one of three kinds of target per joint (``JointMode``): a position
(CSP), a velocity (CSV) or a torque (CST). A drive carries each kind in one CiA 402 mode of
its own, chosen in its config: a position in CSP, IP (interpolated position) or PP (profile
position), a velocity in CSV or PV (profile velocity), a torque in CST. Robot-arm joints
often offer only PP, VL and IP; a controller written for CSP drives them unchanged.

What a mode needs beyond its target is here:

- IP: controlword bit 4 ("enable interpolation") while operation enabled; the target goes
  to 0x60C1:1 (interpolation data record), the drive's interpolation period 0x60C2 is set to
  the loop's dt at bring-up.
- PP: a set-point handshake. A new target is latched by a rising controlword bit 4 ("new
  set-point", with bit 5 "change set immediately"); the drive acknowledges with statusword
  bit 12, and bit 4 goes low again before the next set-point. So a streamed target reaches
  the drive every two to three cycles, which suits slow or vendor-limited drives, not stiff
  control.
- CSP, CSV, CST, PV: the target alone.
"""
from __future__ import annotations

import enum

from ..protocol.joints import JointMode


class DriveMode(enum.IntEnum):
    """The CiA 402 modes (0x6060 values) rocoma-can drives cyclically."""
    PP = 1
    PV = 3
    IP = 7
    CSP = 8
    CSV = 9
    CST = 10


#: the kind of target each drive mode carries
KIND = {DriveMode.PP: JointMode.CSP, DriveMode.IP: JointMode.CSP, DriveMode.CSP: JointMode.CSP,
        DriveMode.PV: JointMode.CSV, DriveMode.CSV: JointMode.CSV,
        DriveMode.CST: JointMode.CST}
#: config names
BY_NAME = {m.name.lower(): m for m in DriveMode}

CW_NEW_SETPOINT = 1 << 4        # PP: rising edge latches the target
CW_ENABLE_INTERPOLATION = 1 << 4  # IP
CW_CHANGE_IMMEDIATELY = 1 << 5  # PP: a new set-point replaces the current one
SW_SETPOINT_ACK = 1 << 12       # PP: set-point acknowledge; IP: interpolation active


def carrier(modes: tuple[DriveMode, ...]) -> list[int]:
    """For one drive: the 0x6060 value that carries each JointMode (index: JointMode value;
    0 where the drive carries nothing of that kind)."""
    table = [0] * 16
    for m in modes:
        table[KIND[m]] = int(m)
    return table


class SetPointHandshake:
    """PP's set-point handshake for every drive, stepped once per cycle.

    ``step`` returns the controlword bits to add to "enable operation" and the target to
    send: a target that differs from the latched one is sent with bit 4 raised; bit 4 stays
    high, with that target, until the drive acknowledges (statusword bit 12); then it goes
    low, and the next target can be raised once the acknowledge has dropped.
    """

    def __init__(self, drives: int) -> None:
        self._raised = [False] * drives
        self._latched: list[int | None] = [None] * drives

    def step(self, i: int, target: int, statusword: int) -> tuple[int, int]:
        ack = statusword & SW_SETPOINT_ACK
        latched = self._latched[i]
        if self._raised[i]:
            if ack:
                self._raised[i] = False
                return CW_CHANGE_IMMEDIATELY, target if latched is None else latched
            return CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY, target if latched is None \
                else latched
        if not ack and target != latched:
            self._raised[i] = True
            self._latched[i] = target
            return CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY, target
        return CW_CHANGE_IMMEDIATELY, target if latched is None else latched

    def reset(self, i: int) -> None:
        """Drive i left operation enabled or the mode: the next target is a new set-point."""
        self._raised[i] = False
        self._latched[i] = None


def interpolation_period(dt: float, fixed_index: int | None = None) -> tuple[int, int]:
    """0x60C2 for a loop period: (value 1..255, index -6..0), value x 10^index = dt, in
    milliseconds where it fits (the unit drives support most widely), else finer, else
    coarser; ``fixed_index``: the drive's own, when it cannot be written. ValueError when no
    such pair gives dt to within 0.1 %."""
    indices = (-3, -4, -5, -6, -2, -1, 0) if fixed_index is None else (fixed_index,)
    for index in indices:
        value = round(dt / 10.0 ** index)
        if 1 <= value <= 255 and abs(value * 10.0 ** index - dt) <= 1e-3 * dt:
            return value, index
    raise ValueError(f"a loop period of {dt} s cannot be an IP interpolation period (0x60C2: "
                     "1..255 x 10^index s" + (f", index fixed at {fixed_index} by the drive)"
                                             if fixed_index is not None else ")"))
