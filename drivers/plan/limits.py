"""A drive's ``limits:`` on the drive itself: the CiA 402 objects bring-up writes and reads
back, and what check-config says about them.

The manager clips every command to the same limits (scaling.py) and watches the following
error (supervision.py); written to the drive they still hold when the manager is gone
(crashed, hung, its cable pulled) for as long as the drive runs on its last command before
its heartbeat consumer switches it off. Only objects the drive's file has, writable, are
written; a limit without one is the manager's alone, and check-config says so.

Joint side (config, SI) to drive units with the drive's own scaling (``increments_per_rev``,
``gear_ratio``, ``rated_torque_nm``: bring-up has checked them against 0x608F, 0x6091 and
0x6076 just before), each rounded outward (a position min down, everything else up): the
drive's limit is never tighter than the manager's, so it never clips a command the manager
let through, and the manager's clip is the one a controller meets. The objects::

    position        0x607D:1 min, :2 max   increments (a negative gear ratio swaps them)
    velocity        0x607F                 increments/s (max profile velocity)
                    0x6080                 motor rpm (max motor speed): |v| x |gear| x 60 / 2 pi
    torque          0x6072                 per mille of the motor's rated torque
    following_error 0x6065                 increments (following error window)
                    0x6066                 ms: 2 x following_error_cycles x the loop period
                                           (the manager e-stops first; the drive backs it up)

The values are computed once per drive, with the loop's period, when the drive is planned
(drive_plan.plan_drive): check-config plans at the config's rate (``run --rate``'s when
given), the hardware at its loop's, and bring-up writes what the plan holds, so a value
check-config accepts is the one bring-up writes.
"""
from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from ..files.capabilities import DriveCapabilities
from ..protocol import cia402
from .config import DriveConfig
from .modes import DriveMode

SOFTWARE_POSITION_LIMIT = cia402.SOFTWARE_POSITION_LIMIT
MAX_PROFILE_VELOCITY = cia402.MAX_PROFILE_VELOCITY
MAX_MOTOR_SPEED = cia402.MAX_MOTOR_SPEED
_ROUNDING = 1e-9  # relative: 0.5 Nm of a 1 Nm motor is 500 per mille, not 501
#: The drive's following error time out is this many times the manager's cycles.
DRIVE_TIMEOUT_FACTOR = 2


class Sdo(Protocol):
    """What writing the limits needs of a drive's SDO client (bringup/named_sdo.py)."""

    def upload(self, index: int, subindex: int) -> bytes: ...

    def download(self, index: int, subindex: int, data: bytes) -> None: ...


@dataclass(frozen=True)
class LimitWrite:
    """One object bring-up writes for one limit, in the drive's units."""
    limit: str      # the ``limits:`` key
    index: int
    subindex: int
    value: int
    unit: str

    @property
    def object(self) -> str:
        return f"0x{self.index:04X}" + (f":{self.subindex}" if self.subindex else "")


#: Per limit, the objects that carry it (index, subindex, name), in the order written.
OBJECTS: dict[str, tuple[tuple[int, int, str], ...]] = {
    "position": ((SOFTWARE_POSITION_LIMIT, 1, "software position limit min"),
                 (SOFTWARE_POSITION_LIMIT, 2, "software position limit max")),
    "velocity": ((MAX_PROFILE_VELOCITY, 0, "max profile velocity"),
                 (MAX_MOTOR_SPEED, 0, "max motor speed")),
    "torque": ((cia402.MAX_TORQUE, 0, "max torque"),),
    "following_error": ((cia402.FOLLOWING_ERROR_WINDOW, 0, "following error window"),
                        (cia402.FOLLOWING_ERROR_TIMEOUT, 0, "following error time out")),
}


def _up(x: float) -> int:
    return math.ceil(x - _ROUNDING * max(1.0, abs(x)))


def _down(x: float) -> int:
    return math.floor(x + _ROUNDING * max(1.0, abs(x)))


def _values(drive: DriveConfig, period: float | None
            ) -> dict[tuple[int, int], tuple[int, str]]:
    """Every object's value in drive units, rounded outward (module docstring); without a
    loop ``period`` (s) no time-based one (0x6066)."""
    lim, gear = drive.limits, abs(drive.gear_ratio)
    per_rad = drive.increments_per_rev * drive.gear_ratio / (2.0 * math.pi)  # signed
    out: dict[tuple[int, int], tuple[int, str]] = {}
    if lim.position is not None:
        ends = sorted(p * per_rad for p in lim.position)
        out[SOFTWARE_POSITION_LIMIT, 1] = (_down(ends[0]), "increments")
        out[SOFTWARE_POSITION_LIMIT, 2] = (_up(ends[1]), "increments")
    if lim.velocity is not None:
        out[MAX_PROFILE_VELOCITY, 0] = (_up(lim.velocity * abs(per_rad)), "increments/s")
        out[MAX_MOTOR_SPEED, 0] = (_up(lim.velocity * gear * 60.0 / (2.0 * math.pi)),
                                   "rpm (motor)")
    if lim.torque is not None:
        out[cia402.MAX_TORQUE, 0] = (
            _up(lim.torque / (drive.rated_torque_nm * gear) * 1000.0),
            "per mille of rated torque")
    if lim.following_error is not None:
        out[cia402.FOLLOWING_ERROR_WINDOW, 0] = (
            _up(lim.following_error * abs(per_rad)), "increments")
        if period is not None:
            out[cia402.FOLLOWING_ERROR_TIMEOUT, 0] = (max(1, _up(
                DRIVE_TIMEOUT_FACTOR * lim.following_error_cycles * period * 1000.0)), "ms")
    return out


def drive_writes(drive: DriveConfig, caps: DriveCapabilities,
                 period: float | None) -> list[LimitWrite]:
    """What bring-up writes for this drive's limits: each set limit's objects its file has,
    writable, at the loop's ``period`` (s; None where no loop runs: 0x6066, a time, is left
    out). ValueError naming the drive, the limit and the object when a value does not fit
    the object's data type (a position beyond INTEGER32 increments, a following error time
    out of more than 65535 ms)."""
    values = _values(drive, period)
    writes: list[LimitWrite] = []
    for limit in drive.limits.given():
        for index, sub, name in OBJECTS[limit]:
            var = caps.variable(index, sub)
            if var is None or not var.writable or (index, sub) not in values:
                continue
            value, unit = values[index, sub]
            try:
                var.encode_raw(value)
            except (struct.error, OverflowError, ValueError):
                why = ""
                if index == cia402.FOLLOWING_ERROR_TIMEOUT and period is not None:
                    why = (f" ({DRIVE_TIMEOUT_FACTOR} x following_error_cycles "
                           f"{drive.limits.following_error_cycles} x {period * 1000:g} ms at "
                           f"{1 / period:g} Hz: fewer cycles, or a higher rate)")
                raise ValueError(f"drive {drive.name!r}: limits.{limit} is {value} {unit} in "
                                 f"0x{index:04X}:{sub} ({name}), which its data type cannot "
                                 f"hold{why}") from None
            writes.append(LimitWrite(limit, index, sub, value, unit))
    return writes


def write_limits(sdo: Sdo, writes: Sequence[LimitWrite], caps: DriveCapabilities) -> None:
    """Write each limit object the drive's plan holds (``drive_writes``), then read it
    back: a drive that keeps another value (it clamps to its own range, or ignores the
    write) fails its bring-up, naming the object and both values. A refusal (SDO abort)
    names the object too (bringup/named_sdo.py)."""
    for w in writes:
        var = caps.variable(w.index, w.subindex)
        assert var is not None  # drive_writes took only objects the file has
        sdo.download(w.index, w.subindex, var.encode_raw(w.value))
        got = var.decode_raw(sdo.upload(w.index, w.subindex)[:len(var) // 8])
        if got != w.value:
            raise RuntimeError(f"limits.{w.limit}: {w.object} written {w.value} {w.unit}, "
                               f"read back {got!r}: the drive clamps or ignores it")


def report(drive: DriveConfig, writes: Sequence[LimitWrite], period: float | None
           ) -> list[str]:
    """check-config's lines: which limits the drive enforces (``writes``, as planned at the
    loop's ``period``: written at bring-up), which only the manager does, and why."""
    lim = drive.limits
    by_limit: dict[str, list[LimitWrite]] = {}
    for w in writes:
        by_limit.setdefault(w.limit, []).append(w)
    drive_side, manager_only = [], []
    for limit in lim.given():
        written = by_limit.get(limit, [])
        if written:
            drive_side.append(f"{limit} (" + ", ".join(
                _shown(w, lim.following_error_cycles, period) for w in written) + ")")
        else:
            names = " or ".join(f"0x{i:04X}" + (f":{s}" if s else "")
                                for i, s, _ in OBJECTS[limit])
            manager_only.append(f"{limit} (its file has no writable {names})")
    manager_only += [f"{key} (old key: under limits: the drive enforces it too)"
                     for key in drive.manager_only_limits()]
    lines = [] if drive_side or manager_only else [
        "limits: none configured (the drive keeps its own, as commissioned)"]
    if drive_side:
        lines.append("limits the drive enforces (written at bring-up): " + "; ".join(drive_side))
    if manager_only:
        lines.append("limits only the manager enforces: " + "; ".join(manager_only))
    if lim.following_error is not None:
        if DriveMode.CSP in drive.modes:
            lines.append(f"following error: e-stop after {lim.following_error_cycles} cycles "
                         f"beyond {lim.following_error:g} rad in CSP")
        else:
            lines.append("following error: the manager watches it in CSP only, which this "
                         "drive does not run")
    return lines


def _shown(w: LimitWrite, cycles: int, period: float | None) -> str:
    if w.index == cia402.FOLLOWING_ERROR_TIMEOUT and period is not None:
        return (f"{w.object} = {w.value} {w.unit} ({DRIVE_TIMEOUT_FACTOR} x {cycles} cycles "
                f"of {period * 1000:g} ms)")
    return f"{w.object} = {w.value} {w.unit}"

