"""Per-drive start-up as a non-blocking state machine, stepped once per cycle.

    WAIT_BOOT ──boot-up / heartbeat (or boot_wait elapsed)──> CONFIGURING
    CONFIGURING ──SDO job done──> STARTING      (job failed, wrong drive ──> FAILED: cause)
    STARTING ──first TPDO──> PROBING, or RESETTING if the statusword says fault
    RESETTING ──fault cleared──> PROBING        (timeout ──> FAILED)
    PROBING ──ready to switch on──> READY       (timeout, EMCY STO ──> FAILED)

All SDO traffic runs in ``configure`` on a worker thread (canopen's SdoClient has no lock:
one job per node at a time, never two threads on one node's SDO). The cycle only looks at
``Future.done()``. A drive that is faulted, whose STO input is low or that does not answer
ends in FAILED with the cause, and the others carry on; so does one whose identity
(0x1018, read before anything is written) is not the one its config or file names
(identity.py).

PROBING sends "shutdown" (0x06) until the drive reports ready to switch on: the power stage
stays off in that state, and a drive whose STO input is low refuses the transition, so it is
found here and left out instead of failing later when a controller wants it enabled.

READY means: NMT operational, PDOs mapped, no fault, torque off. Enabling (switch on, enable
operation) is not part of start-up: the manager starts in FAILPROOF, which sends
disable voltage to every drive, so the enable steps run from the cyclic controlword when a
controller commands a cyclic mode (see hardware.py).
"""
from __future__ import annotations

import enum
import struct
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any

import canopen
from canopen.sdo.client import SdoClient

from ..files.capabilities import DriveCapabilities, PdoChannel
from ..files.identity import IdentityCheck, verify_identity
from ..link.bus import CanopenBus
from ..plan.config import DriveConfig, Supervision, Timeouts
from ..plan.drive_plan import DrivePlan
from ..plan.limits import write_limits
from ..plan.modes import DriveMode, interpolation_period
from ..plan.pdo_layout import Pdo
from ..protocol import cia301, cia402

#: Transmission type: synchronous, every SYNC (RPDO: act on the next SYNC).
SYNC_EVERY_CYCLE = 1
#: 0x1029:1 (CiA 301 error behaviour, communication error): 0 = to pre-operational,
#: 1 = no state change, 2 = to stopped
ERROR_BEHAVIOUR_PRE_OPERATIONAL = 0
ERROR_BEHAVIOUR_NO_CHANGE = 1
_COB_INVALID = 0x8000_0000
_COB_RTR_NOT_ALLOWED = 0x4000_0000

class Phase(enum.IntEnum):
    WAIT_BOOT = 0
    CONFIGURING = 1
    STARTING = 2
    RESETTING = 3
    PROBING = 4
    READY = 5
    FAILED = 6


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


def _configure_pdos(sdo: NamedSdo, pdos: tuple[Pdo, ...],
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


class ObjectRefused(canopen.SdoAbortedError):
    """An SDO abort, naming the object and the value (bring-up's failure line says which
    object the drive refused, not only the abort code)."""

    def __init__(self, code: int, what: str) -> None:
        super().__init__(code)
        self.what = what
        self.aborted = canopen.SdoAbortedError(code)

    def __str__(self) -> str:
        return f"{self.what} refused: {self.aborted}"


class NamedSdo:
    """The drive's SdoClient, each failure naming its object: what configuration uses. For
    axis n of a multi-axis node, a profile object (0x6000-0x67FF) is the axis's own, at
    + (n - 1) x 0x800 (the plan reads the axis at axis 1's indices: capabilities.py)."""

    def __init__(self, sdo: SdoClient, axis: int = 1) -> None:
        self._sdo = sdo
        self.axis = axis

    def upload(self, index: int, subindex: int) -> bytes:
        index = cia402.on_axis(index, self.axis)
        try:
            data: bytes = self._sdo.upload(index, subindex)
            return data
        except canopen.SdoAbortedError as exc:
            raise ObjectRefused(exc.code, f"SDO read of 0x{index:04X}:{subindex}") from exc
        except canopen.SdoCommunicationError as exc:
            raise type(exc)(f"SDO read of 0x{index:04X}:{subindex}: {exc}") from exc

    def download(self, index: int, subindex: int, data: bytes) -> None:
        index = cia402.on_axis(index, self.axis)
        what = f"SDO write of 0x{index:04X}:{subindex} = 0x{int.from_bytes(data, 'little'):X}"
        try:
            self._sdo.download(index, subindex, data)
        except canopen.SdoAbortedError as exc:
            raise ObjectRefused(exc.code, what) from exc
        except canopen.SdoCommunicationError as exc:
            raise type(exc)(f"{what}: {exc}") from exc


CONFIG_ATTEMPTS = 3


class NoAnswer(canopen.SdoCommunicationError):
    """The drive did not answer the first request of a configuration attempt."""


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
    if isinstance(failure, NoAnswer):
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
        raise NoAnswer(f"no SDO reply to 0x1000: {e}") from e
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


#: The longest the SDO switch-off waits for another axis's configuration to free the node's
#: SDO client (seconds): a configuration is a few dozen SDO exchanges.
SWITCH_OFF_WAIT = 5.0


class DriveBringup:
    """Start-up state of one drive; ``step`` is called from the cycle and never blocks."""

    def __init__(self, plan: DrivePlan, node: canopen.RemoteNode, manager_node_id: int,
                 consumer_ms: int, timeouts: Timeouts, dt: float | None = None,
                 lead: DriveBringup | None = None,
                 others: Sequence[tuple[str, IdentityCheck]] = ()) -> None:
        self.dt = dt  # the loop period: an IP drive's interpolation period
        self.others = others  # the other drives' identity checks (configure)
        self.plan = plan
        self.drive = plan.drive
        self.layout = plan.layout
        self.node = node
        self.manager_node_id = manager_node_id
        self.consumer_ms = consumer_ms
        self.timeouts = timeouts
        self.phase = Phase.WAIT_BOOT
        self.since = 0.0
        self.alive = False          # boot-up or heartbeat seen (set by the receive drain)
        self.mapped = False         # our PDO layout is configured: safe to send our RPDOs
        self.failure: str | None = None
        #: the failure was a drive that never answered: the request and its tries
        #: ("did not answer (SDO 0x1000, 3 x 0.5 s)"), else ""
        self.unanswered = ""
        self.reset_cycles = 0       # cycles spent in RESETTING (edge: 0x00 first, then 0x80)
        self.sto_seen = False       # an EMCY 0x5441 arrived during start-up
        self._job: Future[ConfigResult] | None = None
        self._cancelled = threading.Event()  # cancel(): the hardware closes
        # A higher axis of a multi-axis node: configured once its node's lowest axis
        # (``lead``) has configured and started the node, with the node's SDO client
        self.lead = lead
        # canopen's SdoClient has no lock: configuration (worker pool) and the SDO
        # switch-off (switch_off.py) must never overlap on this drive's node
        self._sdo_lock: threading.Lock = lead._sdo_lock if lead is not None \
            else threading.Lock()

    def _locked(self, job: Callable[..., Any], *args: Any) -> Any:
        with self._sdo_lock:
            return job(*args)

    @property
    def name(self) -> str:
        return self.drive.name

    def write_controlword_by_sdo(self, value: int) -> bool:
        """For the SDO switch-off (switch_off.py): False, without writing, while this
        drive's own configuration runs (it is in start-up: torque off). Another axis of its
        node may hold the node's SDO client for its configuration while this one runs
        enabled: then this waits for it (on the switch-off thread, never the cycle's), at
        most ``SWITCH_OFF_WAIT``."""
        if self.phase == Phase.CONFIGURING:
            return False
        if not self._sdo_lock.acquire(timeout=SWITCH_OFF_WAIT):
            return False
        try:
            self.node.sdo.download(cia402.on_axis(cia402.CONTROLWORD, self.drive.axis), 0,
                                   struct.pack("<H", value))
            return True
        finally:
            self._sdo_lock.release()

    def restart(self, now: float, probe_at_once: bool = False) -> None:
        """Back to the beginning (start-up, or recovery of a drive that failed or rebooted)."""
        self.phase = Phase.WAIT_BOOT
        self.since = now - (self.timeouts.boot_wait if probe_at_once else 0.0)
        self.alive = False
        self.failure = None
        self.unanswered = ""
        self.sto_seen = False

    def reset_fault(self, now: float) -> None:
        self._enter(Phase.RESETTING, now)
        self.reset_cycles = 0

    def _enter(self, phase: Phase, now: float) -> None:
        self.phase = phase
        self.since = now

    def _fail(self, cause: str, now: float) -> None:
        self.failure = cause
        self._enter(Phase.FAILED, now)

    def step(self, now: float, executor: Executor, fresh: bool, state: int,
             error_code: int) -> bool:
        """Advance one cycle; returns True on the cycle the drive becomes READY."""
        phase = self.phase
        if phase == Phase.WAIT_BOOT:
            lead = self.lead
            if lead is not None and lead.phase == Phase.FAILED:
                self.unanswered = lead.unanswered  # its node's silence is its own
                self._fail(f"its node's axis {lead.drive.axis} (drive {lead.name!r}) did not "
                           f"start: {lead.failure}", now)
            elif lead is not None and Phase.STARTING <= lead.phase <= Phase.READY \
                    or lead is None and (self.alive
                                         or now - self.since >= self.timeouts.boot_wait):
                self._job = executor.submit(self._locked, configure, self.node, self.plan,
                                            self.manager_node_id, self.consumer_ms, self.dt,
                                            CONFIG_ATTEMPTS, self._cancelled, self.others)
                self._enter(Phase.CONFIGURING, now)
        elif phase == Phase.CONFIGURING:
            job = self._job
            if job is not None and job.done():
                self._job = None
                exc = job.exception()
                if exc is not None:
                    self.unanswered = exc.what if isinstance(exc, Unanswered) else ""
                    self._fail(str(exc) or type(exc).__name__, now)
                    return False
                self.mapped = True
                result = job.result()
                if self.sto_seen or (cia402.state_from_statusword(result.statusword)
                                     == cia402.State402.FAULT
                                     and result.error_code == cia301.EMCY_STO):
                    self._fail("STO input low (safe torque off active)", now)
                    return False
                self._enter(Phase.STARTING, now)
        elif phase == Phase.STARTING:
            if self.sto_seen:
                self._fail("STO input low (safe torque off active)", now)
            elif fresh:
                if state in (cia402.State402.FAULT, cia402.State402.FAULT_REACTION_ACTIVE):
                    self.reset_fault(now)
                else:
                    self._enter(Phase.PROBING, now)
            elif now - self.since > self.timeouts.start:
                self._fail(f"no TPDO within {self.timeouts.start} s of NMT start", now)
        elif phase == Phase.RESETTING:
            self.reset_cycles += 1
            if self.reset_cycles > 2 and fresh and state not in (
                    cia402.State402.FAULT, cia402.State402.FAULT_REACTION_ACTIVE,
                    cia402.State402.UNKNOWN):
                self._enter(Phase.PROBING, now)
            elif now - self.since > self.timeouts.reset:
                why = "STO input low" if error_code == cia301.EMCY_STO else "fault persists"
                self._fail(f"{why} after fault reset (error code 0x{error_code:04X})", now)
        elif phase == Phase.PROBING:
            if self.sto_seen:
                self._fail("STO input low (safe torque off active)", now)
            elif fresh and state == cia402.State402.READY_TO_SWITCH_ON:
                self._enter(Phase.READY, now)
                return True
            elif fresh and state in (cia402.State402.FAULT,
                                     cia402.State402.FAULT_REACTION_ACTIVE):
                self._fail(f"faulted during start-up (error code 0x{error_code:04X})", now)
            elif now - self.since > self.timeouts.reset:
                self._fail(f"refuses shutdown, stays in {cia402.State402(state).name} "
                           "(STO input low?)", now)
        return False

    @property
    def probing(self) -> bool:
        """Send shutdown (0x06) this cycle instead of disable voltage."""
        return self.phase == Phase.PROBING

    @property
    def fault_reset_bit(self) -> bool:
        """Controlword bit 7 this cycle: low on the first RESETTING cycle, then high (edge)."""
        return self.phase == Phase.RESETTING and self.reset_cycles >= 1

    def cancel(self) -> None:
        """The hardware closes: a configuration not begun does not run, a running one ends at
        its SDO wait (answered as an abort) and makes no further attempt, so the close does
        not wait out a silent drive's timeouts and retries (seconds)."""
        self._cancelled.set()
        job = self._job
        if job is not None and not job.cancel() and not job.done():
            cancel_sdo_wait(self.node.sdo)


def create_bringups(plans: Sequence[DrivePlan], networks: Sequence[CanopenBus | None],
                    node: Sequence[tuple[int, ...]], manager_node_id: int, consumer_ms: int,
                    dt: float, supervision: Supervision) -> list[DriveBringup]:
    """Every drive's bring-up on its opened bus: one canopen node per CANopen node, its
    lowest axis first (a higher axis shares that node's SDO client and lock)."""
    made: dict[int, DriveBringup] = {}
    checks = [(f"drive {p.drive.name!r} (node {p.drive.node_id})", p.identity) for p in plans]
    for i in sorted(range(len(plans)), key=lambda k: node[k][0] != k):
        plan, bus, lead = plans[i], networks[i], node[i][0]
        if lead != i:
            made[i] = DriveBringup(plan, made[lead].node, manager_node_id, consumer_ms,
                                   supervision.timeouts, dt, lead=made[lead])
            continue
        assert bus is not None  # opened by the hardware's start
        network = bus.network
        remote = network.add_node(plan.drive.node_id, plan.caps.object_dictionary)
        # The cycle decodes heartbeats and EMCYs itself (receive.py): canopen's consumers
        # of them would only keep an EMCY log that grows for the whole run and log an
        # error per short frame a faulty drive sends.
        network.unsubscribe(cia301.HEARTBEAT + plan.drive.node_id, remote.nmt.on_heartbeat)
        network.unsubscribe(cia301.EMCY + plan.drive.node_id, remote.emcy.on_emcy)
        network.unsubscribe(cia301.NMT, remote.nmt.on_command)
        # No retransmission by default (CiA 301 clients abort on timeout): a late answer
        # to the first copy would be taken as the answer to the next request. configure()
        # repeats a whole failed attempt instead, after stale answers have drained.
        remote.sdo.RESPONSE_TIMEOUT = supervision.sdo_timeout
        remote.sdo.MAX_RETRIES = supervision.sdo_retries + 1  # canopen counts tries (0: forever)
        made[i] = DriveBringup(plan, remote, manager_node_id, consumer_ms,
                               supervision.timeouts, dt,
                               others=[c for k, c in enumerate(checks) if k != i])
    return [made[i] for i in range(len(plans))]
