"""The hardware's status: typed snapshots for services and status reports, and the switch
guard's reason. Everything here only reads (from any thread); JSON is made by the caller
(``HardwareStatus.as_dict``), at the edge where the report leaves the process.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..bringup.drive_bringup import BringupPhase, DriveBringup
from ..link.bus_port import BusPort
from ..plan.config import DriveConfig
from ..protocol import cia301
from ..protocol.cia402 import State402
from ..protocol.joints import JointState
from .homing import HomingJob
from .supervision import Supervisor


@dataclass(frozen=True)
class DriveStatus:
    """A snapshot for status reports and services."""
    name: str
    node_id: int
    phase: str            # a drive_bringup.BringupPhase name: WAIT_BOOT ... READY, FAILED
    cia402_state: str
    enabled: bool
    fault: str | None     # the latched fault or start-up failure, None when healthy
    nmt_state: str = "UNKNOWN"          # from the drive's last heartbeat
    heartbeat_age: float | None = None  # s since that heartbeat arrived; None: none yet
    homing: str = ""                    # "", "enabling", "homing", "homed", "failed: ..."
    #: the latest feedback the drive reports (rad, rad/s, Nm); None: not in its TPDOs
    position: float | None = None
    velocity: float | None = None
    torque: float | None = None


@dataclass(frozen=True)
class BusStatus:
    name: str
    channel: str
    fault: str | None  # the latched bus fault (bus-off, frames refused)
    tx_errors: int     # frames the bus refused
    error_frames: int


@dataclass(frozen=True)
class HardwareStatus:
    """What the manager node serves as 0x2140 and ``rocoma-can status`` prints (with the
    loop's additions, runtime/system.py)."""
    startup_finished: bool
    recovery: str      # "none", "running[: waiting for ...]", "succeeded", "failed"
    bus_fault: str | None
    buses: list[BusStatus]
    drives: list[DriveStatus]

    def as_dict(self) -> dict[str, Any]:
        """JSON-able, by hand: ``dataclasses.asdict`` deep-copies every field recursively,
        in the loop's process (every field here is a plain value)."""
        return {**vars(self), "buses": [dict(vars(b)) for b in self.buses],
                "drives": [dict(vars(d)) for d in self.drives]}


def _reported(value: float, mapped: bool) -> float | None:
    """A feedback value for a status report: None when the drive does not report it (or it
    is not a number: JSON has no NaN)."""
    v = float(value)
    return round(v, 5) if mapped and math.isfinite(v) else None


def drive_status(drives: Sequence[DriveConfig], bringup: Sequence[DriveBringup],
                 supervisor: Supervisor, state: JointState, enabled: np.ndarray,
                 hb_state: Sequence[int], hb_time: np.ndarray,
                 homing: Sequence[HomingJob | None]) -> list[DriveStatus]:
    out = []
    now = time.monotonic()
    for i, d in enumerate(drives):
        b = bringup[i] if bringup else None
        latched = supervisor.latched[i]
        fault = str(latched.cause) if latched is not None else (b.failure if b else None)
        nmt, seen = hb_state[i], float(hb_time[i])
        out.append(DriveStatus(
            d.name, d.node_id, b.phase.name if b else "NOT_STARTED",
            State402(int(state.cia402_state[i])).name, bool(enabled[i]), fault,
            cia301.nmt_name(nmt) if nmt in cia301.NmtState._value2member_map_
            else "UNKNOWN",
            round(now - seen, 3) if math.isfinite(seen) else None,
            job.describe() if (job := homing[i]) is not None else "",
            *(_reported(source[i], kind in (d.feedback or ()))
              for kind, source in (("position", state.position),
                                   ("velocity", state.velocity),
                                   ("torque", state.torque)))))
    return out


def recovery_status(future: Future[bool] | None, drives: Sequence[DriveStatus]) -> str:
    if future is None:
        return "none"
    if not future.done():
        waiting = [f"{d.name} ({d.phase})" for d in drives if d.phase != "READY" or d.fault]
        return "running" + (f": waiting for {', '.join(waiting)}" if waiting else "")
    return "succeeded" if future.result() else "failed"


def bus_status(ports: Sequence[BusPort]) -> list[BusStatus]:
    return [BusStatus(p.name, p.channel, p.latched, p.tx_errors, p.error_frames)
            for p in ports]


def not_ready(drives: Sequence[DriveConfig], bringup: Sequence[DriveBringup],
              supervisor: Supervisor, recovering: bool,
              required: Sequence[int] | None) -> str | None:
    """Why the drives cannot be commanded now, or None: the manager's switch guard (a
    switch into a controller needs its drives brought up and free of latched faults, so
    clearing an e-stop latch never re-arms a faulted drive)."""
    if not bringup:
        return "the drives are not started"
    if recovering:
        return "a recovery is in progress"
    if supervisor.bus_latched is not None:
        return f"bus fault: {supervisor.bus_latched.cause} (recover first)"
    waiting = []
    for i in range(len(bringup)) if required is None else required:
        b, latched, name = bringup[i], supervisor.latched[i], drives[i].name
        if latched is not None:
            waiting.append(f"{name} (fault: {latched.cause}; recover first)")
        elif b.phase != BringupPhase.READY:
            waiting.append(f"{name} ({b.phase.name}" + (f": {b.failure})" if b.failure
                                                         else ")"))
    return "drives not ready: " + ", ".join(waiting) if waiting else None
