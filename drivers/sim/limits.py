"""The simulated drive's own limits, as a CiA 402 drive applies them without its master.

* 0x607D software position limit (:1 min, :2 max, increments): a position target (CSP, IP,
  PP) outside is clamped to the limit, as CiA 402 says for every new target; in the
  velocity and torque modes, where there is no target to clamp, the drive stops at the
  limit: a velocity target towards a limit runs as a position move to the limit no faster
  than the target (the joint slows down and stands at it), and a torque pushing past it is
  replaced by a hold of the limit. Either way the joint ends at the limit, whoever commands it.
* 0x607F max profile velocity (increments/s) and 0x6080 max motor speed (motor rpm): the
  lower one bounds the velocity loop's command in every mode.
* 0x6065 following error window (increments; 0xFFFFFFFF: off) and 0x6066 time out (ms): in
  CSP, a demand (the clamped target) further than the window from the joint for longer
  than the time out is a fault, EMCY 0x8611, statusword bit 13.

(0x6072 max torque is applied where the torque limit is set each SYNC, state_machine.py.)
A value of 0 in 0x607F, 0x6080 or 0x6065 counts as no limit: a file's placeholder, as
elsewhere in the simulator. Positions are the joint's in the drive's target frame
(target / increments_per_rad, as the state machine reads targets).
"""
from __future__ import annotations

import math
from typing import Any

from ..protocol import cia402 as c
from ..protocol.cia301 import ObjectKey
from .objects import AxisKeys

#: 0x6065 value that switches following error monitoring off (CiA 402)
WINDOW_OFF = 0xFFFF_FFFF
_INT32_MIN, _INT32_MAX = -(1 << 31), (1 << 31) - 1
#: the objects whose writes change these limits (axis 1's indices)
OBJECTS = {c.SOFTWARE_POSITION_LIMIT, c.MAX_PROFILE_VELOCITY, c.MAX_MOTOR_SPEED,
           c.FOLLOWING_ERROR_WINDOW, c.FOLLOWING_ERROR_TIMEOUT}


class AxisLimits:
    """One axis's limits in joint units, recomputed when an object or the scaling changes
    (``update``), so a SYNC only compares floats."""

    def __init__(self, keys: AxisKeys, values: dict[ObjectKey, Any]) -> None:
        self._keys = keys
        self._values = values
        self.position_min = -math.inf  # rad
        self.position_max = math.inf
        self.velocity = math.inf       # rad/s
        self.window = math.inf         # rad
        self.timeout = 0.0             # s
        self._over = 0.0               # s the following error has been beyond the window

    def update(self, increments_per_rad: float, motor_revs_per_rad: float) -> None:
        v, k = self._values, self._keys
        low, high = v.get(k.position_limit_min), v.get(k.position_limit_max)
        if low is None or high is None or low >= high:  # no object, or an empty range
            self.position_min, self.position_max = -math.inf, math.inf
        else:  # the INTEGER32 range's ends (the file's default): no limit that side
            self.position_min = -math.inf if low <= _INT32_MIN else low / increments_per_rad
            self.position_max = math.inf if high >= _INT32_MAX else high / increments_per_rad
        limits = [math.inf]
        profile = v.get(k.max_profile_velocity)
        if profile:
            limits.append(profile / increments_per_rad)
        rpm = v.get(k.max_motor_speed)
        if rpm:
            limits.append(rpm / 60.0 / motor_revs_per_rad)
        self.velocity = min(limits)
        window = v.get(k.following_error_window)
        self.window = math.inf if not window or window == WINDOW_OFF \
            else window / increments_per_rad
        self.timeout = v.get(k.following_error_timeout, 0) / 1000.0
        self._over = 0.0

    def clamp(self, target: float) -> float:
        """A position target inside the software position limits."""
        return self.position_min if target < self.position_min else \
            self.position_max if target > self.position_max else target

    def heading_to(self, velocity: float) -> float | None:
        """The limit a velocity target heads to (None: none in that direction). The drive
        then runs a position move to it no faster than the target: the same motion far from
        the limit, a stop at it (and exact within the step, however long the step is)."""
        if velocity > 0.0 and self.position_max < math.inf:
            return self.position_max
        if velocity < 0.0 and self.position_min > -math.inf:
            return self.position_min
        return None

    def pushed_past(self, torque: float, position: float) -> float | None:
        """The limit to hold when ``torque`` pushes the joint beyond it (None: it does not)."""
        if torque > 0.0 and position >= self.position_max:
            return self.position_max
        if torque < 0.0 and position <= self.position_min:
            return self.position_min
        return None

    def following_error(self, demand: float, position: float, dt: float) -> bool:
        """True once the demand has been further than the window from the joint for longer
        than the time out (CSP, each SYNC)."""
        if abs(demand - position) <= self.window:
            self._over = 0.0
            return False
        self._over += dt
        return self._over > self.timeout

    def reset(self) -> None:
        self._over = 0.0
