"""Joint state and command shared by the driver and every controller of one manager.

Plain numpy arrays in SI units, allocated once: the cycle writes into them in place, so a
controller may keep references to the arrays (``q = self.state.position``) across cycles.
"""
from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .cia402 import State402


class JointMode(enum.IntEnum):
    """What a controller asks of one joint. The values of CSP/CSV/CST are the CiA 402 modes."""
    TORQUE_OFF = 0  # controlword disable voltage: power stage off, joint coasts
    QUICK_STOP = 1  # controlword quick stop: the drive's own ramp (0x605A)
    CSP = 8         # cyclic synchronous position: position target (+ velocity/torque offset)
    CSV = 9         # cyclic synchronous velocity: velocity target (+ torque offset)
    CST = 10        # cyclic synchronous torque: torque target


def _names(names: Sequence[str] | int) -> tuple[str, ...]:
    if isinstance(names, int):
        return tuple(f"joint{i}" for i in range(names))
    out = tuple(names)
    if len(set(out)) != len(out):
        raise ValueError(f"joint names must be unique, got {list(out)}")
    return out


@dataclass
class JointState:
    """What the drives reported in the latest cycle."""
    names: tuple[str, ...]
    position: np.ndarray = field(repr=False)      # rad
    velocity: np.ndarray = field(repr=False)      # rad/s
    torque: np.ndarray = field(repr=False)        # Nm
    cia402_state: np.ndarray = field(repr=False)  # int8 State402 values
    statusword: np.ndarray = field(repr=False)    # uint16
    error_code: np.ndarray = field(repr=False)    # uint16, 0x603F / last EMCY code
    fresh: np.ndarray = field(repr=False)         # bool: a TPDO arrived in this cycle
    stamp: np.ndarray = field(repr=False)         # float64, time.monotonic() of the TPDO
    time: float = 0.0                             # monotonic time of this cycle's SYNC

    @classmethod
    def zeros(cls, names: Sequence[str] | int) -> JointState:
        names = _names(names)
        n = len(names)
        return cls(
            names=names,
            position=np.zeros(n), velocity=np.zeros(n), torque=np.zeros(n),
            cia402_state=np.full(n, State402.UNKNOWN, dtype=np.int8),
            statusword=np.zeros(n, dtype=np.uint16),
            error_code=np.zeros(n, dtype=np.uint16),
            fresh=np.zeros(n, dtype=bool),
            stamp=np.zeros(n),
        )

    @property
    def n(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint named {name!r}; joints are {list(self.names)}") from None


@dataclass
class JointCommand:
    """What the controllers ask of the drives in this cycle; the driver encodes it."""
    names: tuple[str, ...]
    mode: np.ndarray = field(repr=False)      # uint8 JointMode values
    position: np.ndarray = field(repr=False)  # rad (CSP target)
    velocity: np.ndarray = field(repr=False)  # rad/s (CSV target, CSP offset)
    torque: np.ndarray = field(repr=False)    # Nm (CST target, CSP/CSV offset)

    @classmethod
    def zeros(cls, names: Sequence[str] | int) -> JointCommand:
        names = _names(names)
        n = len(names)
        return cls(names=names, mode=np.zeros(n, dtype=np.uint8),
                   position=np.zeros(n), velocity=np.zeros(n), torque=np.zeros(n))

    @property
    def n(self) -> int:
        return len(self.names)

    def torque_off(self) -> None:
        """Every joint: power stage off, targets zero. In place: no allocation."""
        self.mode.fill(JointMode.TORQUE_OFF)
        self.position.fill(0.0)
        self.velocity.fill(0.0)
        self.torque.fill(0.0)
