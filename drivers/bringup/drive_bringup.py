"""Per-drive start-up as a non-blocking state machine, stepped once per cycle.

    WAIT_BOOT ──boot-up / heartbeat (or boot_wait elapsed)──> CONFIGURING
    CONFIGURING ──SDO job done──> STARTING      (job failed, wrong drive ──> FAILED: cause)
    STARTING ──first TPDO──> PROBING, or RESETTING if the statusword says fault
    RESETTING ──fault cleared──> PROBING        (timeout ──> FAILED)
    PROBING ──ready to switch on──> READY       (timeout, EMCY STO ──> FAILED)

All SDO traffic runs in ``configure`` (configure.py) on a worker thread (canopen's
SdoClient has no lock: one job per node at a time, never two threads on one node's SDO). The
cycle only looks at ``Future.done()``. A drive that is faulted, whose STO input is low or
that does not answer ends in FAILED with the cause, and the others carry on; so does one
whose identity (0x1018, read before anything is written) is not the one its config or file
names (files/identity.py).

PROBING sends "shutdown" (0x06) until the drive reports ready to switch on: the power stage
stays off in that state, and a drive whose STO input is low refuses the transition, so it is
found here and left out instead of failing later when a controller wants it enabled.

READY means: NMT operational, PDOs mapped, no fault, torque off. Enabling (switch on, enable
operation) is not part of start-up: the manager starts in FAILPROOF, which sends
disable voltage to every drive, so the enable steps run from the cyclic controlword when a
controller commands a cyclic mode (cycle/enable.py).
"""
from __future__ import annotations

import enum
import struct
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future
from typing import Any

import canopen

from ..files.identity import IdentityCheck
from ..link.bus import CanopenBus
from ..plan.config import Supervision, Timeouts
from ..plan.drive_plan import DrivePlan
from ..protocol import cia301, cia402
from .configure import CONFIG_ATTEMPTS, ConfigResult, Unanswered, cancel_sdo_wait, configure


class BringupPhase(enum.IntEnum):
    """Where a drive's start-up is (the diagram above)."""
    WAIT_BOOT = 0
    CONFIGURING = 1
    STARTING = 2
    RESETTING = 3
    PROBING = 4
    READY = 5
    FAILED = 6


#: A drive's failure when its STO input is low (an EMCY 0x5441, or a fault with that code)
STO_ACTIVE = "STO input low (safe torque off active)"
_FAULTED = (cia402.State402.FAULT, cia402.State402.FAULT_REACTION_ACTIVE)

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
        self.phase = BringupPhase.WAIT_BOOT
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
        if self.phase == BringupPhase.CONFIGURING:
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
        self.phase = BringupPhase.WAIT_BOOT
        self.since = now - (self.timeouts.boot_wait if probe_at_once else 0.0)
        self.alive = False
        self.failure = None
        self.unanswered = ""
        self.sto_seen = False

    def reset_fault(self, now: float) -> None:
        self._enter(BringupPhase.RESETTING, now)
        self.reset_cycles = 0

    def _enter(self, phase: BringupPhase, now: float) -> None:
        self.phase = phase
        self.since = now

    def _fail(self, cause: str, now: float) -> None:
        self.failure = cause
        self._enter(BringupPhase.FAILED, now)

    def step(self, now: float, executor: Executor, fresh: bool, state: int,
             error_code: int) -> bool:
        """Advance one cycle; returns True on the cycle the drive becomes READY. ``fresh``:
        every TPDO of the drive arrived this cycle; ``state``, ``error_code``: what they
        said (CiA 402 state, 0x603F or the last EMCY)."""
        phase = self.phase
        if phase == BringupPhase.WAIT_BOOT:
            self._wait_boot(now, executor)
        elif phase == BringupPhase.CONFIGURING:
            self._configuring(now)
        elif phase == BringupPhase.STARTING:
            self._starting(now, fresh, state)
        elif phase == BringupPhase.RESETTING:
            self._resetting(now, fresh, state, error_code)
        elif phase == BringupPhase.PROBING:
            return self._probing(now, fresh, state, error_code)
        return False

    def _wait_boot(self, now: float, executor: Executor) -> None:
        """The configuration job starts once the drive is alive (or boot_wait is over); a
        higher axis's once its node's lowest axis has started the node."""
        lead = self.lead
        if lead is not None and lead.phase == BringupPhase.FAILED:
            self.unanswered = lead.unanswered  # its node's silence is its own
            self._fail(f"its node's axis {lead.drive.axis} (drive {lead.name!r}) did not "
                       f"start: {lead.failure}", now)
        elif lead is not None and BringupPhase.STARTING <= lead.phase <= BringupPhase.READY \
                or lead is None and (self.alive
                                     or now - self.since >= self.timeouts.boot_wait):
            self._job = executor.submit(self._locked, configure, self.node, self.plan,
                                        self.manager_node_id, self.consumer_ms, self.dt,
                                        CONFIG_ATTEMPTS, self._cancelled, self.others)
            self._enter(BringupPhase.CONFIGURING, now)

    def _configuring(self, now: float) -> None:
        job = self._job
        if job is None or not job.done():
            return
        self._job = None
        exc = job.exception()
        if exc is not None:
            self.unanswered = exc.what if isinstance(exc, Unanswered) else ""
            self._fail(str(exc) or type(exc).__name__, now)
            return
        self.mapped = True
        result = job.result()
        if self.sto_seen or (cia402.state_from_statusword(result.statusword)
                             == cia402.State402.FAULT
                             and result.error_code == cia301.EMCY_STO):
            self._fail(STO_ACTIVE, now)
            return
        self._enter(BringupPhase.STARTING, now)

    def _starting(self, now: float, fresh: bool, state: int) -> None:
        if self.sto_seen:
            self._fail(STO_ACTIVE, now)
        elif fresh:
            if state in _FAULTED:
                self.reset_fault(now)
            else:
                self._enter(BringupPhase.PROBING, now)
        elif now - self.since > self.timeouts.start:
            self._fail(f"no TPDO within {self.timeouts.start} s of NMT start", now)

    def _resetting(self, now: float, fresh: bool, state: int, error_code: int) -> None:
        self.reset_cycles += 1
        if self.reset_cycles > 2 and fresh and state not in _FAULTED \
                and state != cia402.State402.UNKNOWN:
            self._enter(BringupPhase.PROBING, now)
        elif now - self.since > self.timeouts.reset:
            why = "STO input low" if error_code == cia301.EMCY_STO else "fault persists"
            self._fail(f"{why} after fault reset (error code 0x{error_code:04X})", now)

    def _probing(self, now: float, fresh: bool, state: int, error_code: int) -> bool:
        if self.sto_seen:
            self._fail(STO_ACTIVE, now)
        elif fresh and state == cia402.State402.READY_TO_SWITCH_ON:
            self._enter(BringupPhase.READY, now)
            return True
        elif fresh and state in _FAULTED:
            self._fail(f"faulted during start-up (error code 0x{error_code:04X})", now)
        elif now - self.since > self.timeouts.reset:
            self._fail(f"refuses shutdown, stays in {cia402.State402(state).name} "
                       "(STO input low?)", now)
        return False

    @property
    def probing(self) -> bool:
        """Send shutdown (0x06) this cycle instead of disable voltage."""
        return self.phase == BringupPhase.PROBING

    @property
    def fault_reset_bit(self) -> bool:
        """Controlword bit 7 this cycle: low on the first RESETTING cycle, then high (edge)."""
        return self.phase == BringupPhase.RESETTING and self.reset_cycles >= 1

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
