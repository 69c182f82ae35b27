"""A drive's configuration before NMT start, by SDO, on a configuration worker.

What ``configure`` writes, in order: the node to pre-operational (PDO mapping needs it),
then checks before anything is written (a CiA 402 device, its identity 0x1018, its modes
0x6502, its scaling 0x608F/0x6091/0x6076 against the config), the drive-side limits, every
PDO channel (ours mapped the CiA 301 way, invalid first; the rest switched off), the
heartbeat producer or node guarding, what makes the drive let go when the manager is lost
(heartbeat consumer, 0x6007, 0x1029), the homing method, the interpolation period, the
first mode; then NMT start. The drive's bring-up (drive_bringup.py) runs it as one job
and only looks at its future.
"""
from __future__ import annotations

import struct
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import canopen
from canopen.sdo.client import SdoClient

from ..files.capabilities import DriveCapabilities, PdoChannel
from ..files.identity import IdentityCheck, verify_identity
from ..plan.config import DriveConfig
from ..plan.drive_plan import DrivePlan
from ..plan.limits import write_limits
from ..plan.modes import DriveMode, interpolation_period
from ..plan.pdo_layout import LayoutPdo
from ..protocol import cia301, cia402
from .named_sdo import NamedSdo

#: Transmission type: synchronous, every SYNC (RPDO: act on the next SYNC).
SYNC_EVERY_CYCLE = 1
#: 0x1029:1 (CiA 301 error behaviour, communication error): 0 = to pre-operational,
#: 1 = no state change, 2 = to stopped
ERROR_BEHAVIOUR_PRE_OPERATIONAL = 0
ERROR_BEHAVIOUR_NO_CHANGE = 1
_COB_INVALID = 0x8000_0000
_COB_RTR_NOT_ALLOWED = 0x4000_0000


@dataclass(frozen=True)
class ConfigResult:
    statusword: int
    error_code: int


def _u8(v: int) -> bytes:
    return struct.pack("<B", v)


def _u16(v: int) -> bytes:
    return struct.pack("<H", v)


def _u32(v: int) -> bytes:
    return struct.pack("<I", v)


def _configure_pdos(sdo: NamedSdo, pdos: tuple[LayoutPdo, ...],
                    channels: tuple[PdoChannel, ...]) -> None:
    """Every PDO channel the drive has: ours mapped (a fixed one left as it is), each sent
    or applied every SYNC where the drive lets us say so; the others switched off."""
    used = {p.number: p for p in pdos}
    for ch in channels:
        comm, mapping = ch.communication_index, ch.mapping_index
        pdo = used.get(ch.number)
        keep = ch.cob_id & _COB_RTR_NOT_ALLOWED  # a drive may insist on its bit 30
        if ch.cob_id_writable:  # invalid first: CiA 301 forbids remapping a valid PDO
            sdo.download(comm, 1, _u32(_COB_INVALID | keep | (ch.cob_id & 0x7FF
                                                              or (pdo.cob_id if pdo else 0))))
        if pdo is None:
            continue
        if not pdo.fixed:
            sdo.download(mapping, 0, _u8(0))
            for j, entry in enumerate(pdo.entries, start=1):
                index = cia402.on_axis(entry.mapping >> 16, sdo.axis)  # the axis's object
                sdo.download(mapping, j, _u32(index << 16 | entry.mapping & 0xFFFF))
            sdo.download(mapping, 0, _u8(len(pdo.entries)))
        if ch.transmission_type_writable:
            sdo.download(comm, 2, _u8(SYNC_EVERY_CYCLE))
        if ch.cob_id_writable:
            sdo.download(comm, 1, _u32(keep | pdo.cob_id))


def _read_u32(sdo: NamedSdo, index: int, subindex: int) -> int | None:
    """An optional object: None when the drive does not have it."""
    try:
        value: int = struct.unpack("<I", sdo.upload(index, subindex)[:4].ljust(4, b"\0"))[0]
        return value
    except canopen.SdoAbortedError:
        return None


def _check_scaling(sdo: NamedSdo, drive: DriveConfig) -> None:
    """Where the drive states its scaling (0x608F, 0x6091, 0x6076), the config must agree:
    a wrong increments_per_rev or gear ratio would scale every target wrongly."""
    checks: list[tuple[str, float, float, str]] = []
    inc = _read_u32(sdo, cia402.POSITION_ENCODER_RESOLUTION, 1)
    revs = _read_u32(sdo, cia402.POSITION_ENCODER_RESOLUTION, 2)
    if inc and revs:
        checks.append(("increments_per_rev", drive.increments_per_rev, inc / revs, "0x608F"))
    motor = _read_u32(sdo, cia402.GEAR_RATIO, 1)
    shaft = _read_u32(sdo, cia402.GEAR_RATIO, 2)
    if motor and shaft:
        checks.append(("gear_ratio", abs(drive.gear_ratio), motor / shaft, "0x6091"))
    rated = _read_u32(sdo, cia402.RATED_TORQUE, 0)
    if rated:
        checks.append(("rated_torque_nm", drive.rated_torque_nm, rated / 1000.0, "0x6076"))
    for name, configured, reported, where in checks:
        if abs(configured - reported) > 1e-9 * max(abs(reported), 1.0):
            raise RuntimeError(f"config {name} = {configured:g} but the drive reports "
                               f"{reported:g} ({where})")


def life_time_factor(guard_ms: int, consumer_ms: int) -> int:
    """0x100D for a guarded drive: its life time (guard time x factor) as close to the
    heartbeat consumer time as the factor allows (the same loss time either way), at least
    2 (one late request is not a loss), at most 255 (UNSIGNED8)."""
    return max(2, min(255, -(-consumer_ms // guard_ms)))


def _arm_guarding(sdo: NamedSdo, plan: DrivePlan, consumer_ms: int) -> None:
    """The drive's heartbeat producer, or node guarding: guard time and life time factor
    (the drive's life guarding starts with the manager's first request, sent from the
    cycle once the drive is configured). A guarded drive's producer, where it has one, is
    set to 0: CiA 301 lets a node answer guarding only while it produces no heartbeat."""
    drive, caps = plan.drive, plan.caps
    if not plan.guarded:
        sdo.download(cia301.PRODUCER_HEARTBEAT_TIME, 0, _u16(drive.heartbeat_ms))
        return
    if caps.writable(cia301.PRODUCER_HEARTBEAT_TIME):
        sdo.download(cia301.PRODUCER_HEARTBEAT_TIME, 0, _u16(0))
    sdo.download(cia301.GUARD_TIME, 0, _u16(drive.heartbeat_ms))
    sdo.download(cia301.LIFE_TIME_FACTOR, 0,
                 _u8(life_time_factor(drive.heartbeat_ms, consumer_ms)))


def _arm_against_manager_loss(sdo: NamedSdo, caps: DriveCapabilities, manager_node_id: int,
                              consumer_ms: int, node_level: bool = True) -> None:
    """What makes the drive let go when the manager dies or hangs, as far as its objects
    allow (drive_plan.py refuses a drive with none of them unless the config accepts it):
    the heartbeat consumer watches the manager; 0x6007 = disable voltage switches the power
    stage off on its timeout; a 0x1029:1 of "no state change" becomes "pre-operational", so
    the drive at least stops applying RPDOs. The consumer and 0x1029 are the node's, 0x6007
    each axis's own."""
    if caps.heartbeat_consumer and node_level:
        sdo.download(cia301.CONSUMER_HEARTBEAT_TIME, 1,
                     _u32((manager_node_id << 16) | consumer_ms))
    if caps.abort_connection:
        sdo.download(cia402.ABORT_CONNECTION_OPTION, 0,
                     struct.pack("<h", cia402.AbortConnectionOption.DISABLE_VOLTAGE))
    if node_level and caps.error_behaviour and sdo.upload(cia301.ERROR_BEHAVIOR, 1)[:1] == _u8(
            ERROR_BEHAVIOUR_NO_CHANGE):
        sdo.download(cia301.ERROR_BEHAVIOR, 1, _u8(ERROR_BEHAVIOUR_PRE_OPERATIONAL))


CONFIG_ATTEMPTS = 3


class FirstRequestUnanswered(canopen.SdoCommunicationError):
    """The drive did not answer the first request (0x1000) of a configuration attempt: a
    drive that is not there, as against one whose answers were garbled later on."""


class Unanswered(RuntimeError):
    """The drive answered no attempt of its configuration (``what``: the request and its
    tries); the message adds what to check."""

    def __init__(self, what: str) -> None:
        super().__init__(f"{what}: power, wiring, node id, bitrate?")
        self.what = what


#: what a cancelled configuration's SDO wait is handed as its answer (cancel_sdo_wait): an
#: abort (CiA 301 0x08000000, general error), so canopen's client raises at once
_CANCELLED = struct.pack("<BHBI", 0x80, 0, 0, 0x08000000)


def cancel_sdo_wait(sdo: SdoClient) -> None:
    """End the wait of a request on ``sdo`` (the hardware closes): canopen's client waits
    for the drive's answer on its ``responses`` queue for up to its timeout (per try), a
    drive that is not there never answers, and the close would wait it out."""
    sdo.responses.put(_CANCELLED)


def configure(node: canopen.RemoteNode, plan: DrivePlan, manager_node_id: int,
              consumer_ms: int, dt: float | None = None,
              attempts: int = CONFIG_ATTEMPTS,
              cancelled: threading.Event | None = None,
              others: Sequence[tuple[str, IdentityCheck]] = ()) -> ConfigResult:
    """Everything a drive needs before NMT start, by SDO; runs on the configuration worker.

    A garbled exchange is transient on a loaded bus: canopen retransmits a request on
    timeout, and the late answer to the first copy then arrives as the answer to the next
    request ("Unexpected response"); the hardware layer therefore turns canopen's
    retransmission off. The configuration is idempotent, so it is repeated
    whole (at most ``attempts`` times) after a pause in which stale answers arrive and are
    dropped. Refusals (SDO aborts) and a drive that never answers are final.
    Raises with a message naming the step when the drive refuses or does not answer;
    once ``cancelled`` is set (the hardware closes) no attempt follows and the pause ends.
    ``others``: the other drives' identity checks (a device that is one of them: swapped).
    """
    for attempt in range(1, attempts + 1):
        if cancelled is not None and cancelled.is_set():
            raise RuntimeError("cancelled: the hardware closes")
        try:
            return _configure_once(node, plan, manager_node_id, consumer_ms, dt, others)
        except struct.error as exc:  # canopen unpacking an answer shorter than an SDO frame
            raise RuntimeError(f"a malformed SDO answer (shorter than an SDO frame: {exc}): "
                               f"is node {node.id} the CANopen drive the config says, or is "
                               "another device answering at its id?") from exc
        except canopen.SdoCommunicationError as exc:
            failure = exc
            if attempt < attempts:
                pause = 2 * node.sdo.RESPONSE_TIMEOUT
                if cancelled is not None:
                    cancelled.wait(pause)
                else:
                    time.sleep(pause)
    if isinstance(failure, FirstRequestUnanswered):
        raise Unanswered(f"did not answer (SDO 0x1000, {attempts} x "
                         f"{node.sdo.RESPONSE_TIMEOUT:g} s)") from failure
    raise RuntimeError(f"SDO exchange failed {attempts} times: {failure}") from failure


def _configure_once(node: canopen.RemoteNode, plan: DrivePlan, manager_node_id: int,
                    consumer_ms: int, dt: float | None,
                    others: Sequence[tuple[str, IdentityCheck]]) -> ConfigResult:
    sdo, drive, layout, caps = NamedSdo(node.sdo, plan.drive.axis), plan.drive, plan.layout, \
        plan.caps
    # The node's lowest axis configures the node: NMT, its heartbeat or guarding, its
    # consumer. A higher axis comes after it (DriveBringup.step), in OPERATIONAL, and maps
    # its own PDO channels the CiA 301 way (invalid first), leaving the running axis be.
    node_level = plan.leads_node
    if node_level:
        node.nmt.send_command(cia301.NmtCommand.PRE_OPERATIONAL)  # PDO mapping needs pre-op
    try:
        device_type = struct.unpack("<I", sdo.upload(cia301.DEVICE_TYPE, 0)[:4])[0]
    except canopen.SdoCommunicationError as e:
        raise FirstRequestUnanswered(f"no SDO reply to 0x1000: {e}") from e
    if device_type & 0xFFFF != 402:
        raise RuntimeError(f"is not a CiA 402 drive (0x1000 = 0x{device_type:08X})")
    if node_level:  # before anything is written: a wrong drive must not be reconfigured
        verify_identity(sdo, plan.identity, others)
    for axis in plan.other_axes:  # pre-operational stops their RPDOs: switched off first
        NamedSdo(node.sdo, axis).download(cia402.CONTROLWORD, 0, _u16(0))
    try:
        supported = struct.unpack("<I", sdo.upload(cia402.SUPPORTED_DRIVE_MODES, 0)[:4])[0]
    except canopen.SdoAbortedError:
        supported = None  # optional object: trust the config
    if supported is not None:
        missing = [m.name for m in drive.modes if not supported & (1 << (int(m) - 1))]
        if missing:
            raise RuntimeError(f"does not support mode(s) {missing} (0x6502 = 0x{supported:X})")
    _check_scaling(sdo, drive)
    write_limits(sdo, plan.limit_writes, caps)  # drive units: after its scaling is checked
    _configure_pdos(sdo, layout.rpdos, caps.rpdos)
    _configure_pdos(sdo, layout.tpdos, caps.tpdos)
    if node_level:
        _arm_guarding(sdo, plan, consumer_ms)
    _arm_against_manager_loss(sdo, caps, manager_node_id, consumer_ms, node_level)
    if drive.homing_method is not None:  # drive_plan.py checked that 0x6098 is writable
        sdo.download(cia402.HOMING_METHOD, 0, struct.pack("<b", drive.homing_method))
    if DriveMode.IP in drive.modes and dt is not None \
            and caps.writable(cia402.INTERPOLATION_PERIOD, 1):  # IP steps once per cycle
        fixed = None if caps.writable(cia402.INTERPOLATION_PERIOD, 2) else \
            caps.value(cia402.INTERPOLATION_PERIOD, 2)
        value, index = interpolation_period(dt, fixed)
        sdo.download(cia402.INTERPOLATION_PERIOD, 1, _u8(value))
        if fixed is None:
            sdo.download(cia402.INTERPOLATION_PERIOD, 2, struct.pack("<b", index))
    sdo.download(cia402.MODES_OF_OPERATION, 0, struct.pack("<b", int(drive.modes[0])))
    statusword = struct.unpack("<H", sdo.upload(cia402.STATUSWORD, 0)[:2])[0]
    try:
        error_code = struct.unpack("<H", sdo.upload(cia402.ERROR_CODE, 0)[:2])[0]
    except canopen.SdoAbortedError:
        error_code = 0
    if node_level:
        node.nmt.send_command(cia301.NmtCommand.START)
    return ConfigResult(statusword, error_code)
