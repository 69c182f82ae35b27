"""Bus units <-> SI units for all joints at once.

The factors are computed once from the drive configs; the cycle multiplies whole arrays into
pre-allocated outputs (``out=``), so decoding 24 joints costs the same few numpy calls as 1.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .config import DriveConfig

INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1
INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1


class Scaling:
    """rad / rad/s / Nm per bus unit, per joint, plus the command limits."""

    def __init__(self, drives: Sequence[DriveConfig]) -> None:
        n = len(drives)
        #: rad per increment (also rad/s per increment/s)
        self.position = np.array([2.0 * math.pi / (d.increments_per_rev * d.gear_ratio)
                                  for d in drives])
        self.velocity = self.position.copy()
        #: Nm (joint side) per per-mille of rated motor torque
        self.torque = np.array([d.rated_torque_nm * d.gear_ratio / 1000.0 for d in drives])
        self._inv_position = 1.0 / self.position
        self._inv_velocity = 1.0 / self.velocity
        self._inv_torque = 1.0 / self.torque
        self.position_min = np.array([d.position_min for d in drives])
        self.position_max = np.array([d.position_max for d in drives])
        self.max_velocity = np.array([d.max_velocity for d in drives])
        self.max_torque = np.array([d.max_torque_nm for d in drives])
        self._min_velocity = -self.max_velocity
        self._min_torque = -self.max_torque
        self._tmp = np.zeros(n)

    def decode(self, raw: np.ndarray, factor: np.ndarray, out: np.ndarray) -> None:
        """out = raw * factor, in place."""
        np.multiply(raw, factor, out=out)

    def encode_position(self, si: np.ndarray, out: np.ndarray) -> None:
        self._encode(si, self._inv_position, INT32_MIN, INT32_MAX, out)

    def encode_velocity(self, si: np.ndarray, out: np.ndarray) -> None:
        self._encode(si, self._inv_velocity, INT32_MIN, INT32_MAX, out)

    def encode_torque(self, si: np.ndarray, out: np.ndarray) -> None:
        self._encode(si, self._inv_torque, INT16_MIN, INT16_MAX, out)

    def _encode(self, si: np.ndarray, inv: np.ndarray, lo: int, hi: int, out: np.ndarray) -> None:
        # NaN never reaches here (limit_command rejects it); clip before the integer cast so a
        # huge target saturates instead of wrapping around to the opposite sign.
        tmp = self._tmp
        np.multiply(si, inv, out=tmp)
        np.rint(tmp, out=tmp)
        np.minimum(tmp, hi, out=tmp)  # minimum/maximum: a third of np.clip's call overhead
        np.maximum(tmp, lo, out=tmp)
        np.copyto(out, tmp, casting="unsafe")

    def clip_command(self, position: np.ndarray, velocity: np.ndarray,
                     torque: np.ndarray) -> None:
        """Clip targets to the configured joint limits, in place."""
        np.minimum(position, self.position_max, out=position)
        np.maximum(position, self.position_min, out=position)
        np.minimum(velocity, self.max_velocity, out=velocity)
        np.maximum(velocity, self._min_velocity, out=velocity)
        np.minimum(torque, self.max_torque, out=torque)
        np.maximum(torque, self._min_torque, out=torque)
