"""The CAN hardware layer: N CiA 402 drives as one JointState / JointCommand pair.

One cycle, on the one thread that owns the loop (``rocoma_can.runtime.loop.run_cycle`` is
the one place that writes this order)::

    events = hw.read(now)    drain received frames -> JointState; bring-up and recovery
                             steps; supervision -> what the manager must act on
    event.apply(manager)     each e-stop, failproof stop, finished recovery, before update
    manager.update()         the active layer writes JointCommand
    hw.write(state, n)       RPDOs (or torque-off frames) for every drive, SYNC, manager
                             heartbeat, guard requests (n: the manager's committed switches)

The hardware never holds the manager. Its jobs, one module each: receive.py (dispatch of
every received frame), supervision.py (deadlines and fault latches), bringup/ (start-up),
command.py (JointCommand -> controlword, mode, targets), frames_out.py (every frame sent,
torque-off first), stop_requests.py (what a read found), node_guarding.py, recovery.py,
status.py; this module builds the drive table they all take (drive_table.py) and wires them.

The safety path, top to bottom (each step names where it lives):

1. A drive goes wrong. Supervision (supervision.py) turns every symptom into a FaultEvent:
   EMCY, statusword fault bit, heartbeat (or node guarding answer) deadline or a non-
   operational state in it, TPDOs missing for k cycles, a drive dropping out of operation
   enabled or not enabling in time (enable.py, command.py). A whole bus can fail too: a
   bus-off error frame or the bus refusing frames in ``tpdo_timeout_cycles`` cycles in a row
   (``BusPort.bus_off`` and ``BusPort.end_of_write``, bus_port.py) is a fault of every drive
   on it (``ReadFindings.bus_failed``, stop_requests.py). Frames arrive on the buses' reader
   thread (bus.py), which only appends them to each bus's deque; ``read`` drains every bus
   on the cycle thread (receive.py), so no lock is shared with a slow thread. ``read`` first
   reads the buses itself where the reader thread is not reading (BusReader.drain_now, a
   lock only tried): a starved reader thread delays nothing. An e-stop frame
   (``estop_cob_id``, any bus) is drained the same way and reaches the manager before this
   cycle's update.
2. The faulted drive gets torque-off frames from the same cycle on (command.py: a latched
   drive is never sent anything but controlword 0x0000), until recovery, and controlword
   0x0000 once by SDO from a thread of its own (``ReadFindings.deliver``, switch_off.py):
   a drive that no longer applies RPDOs (pre-operational, ignoring SYNC) still switches off.
3. ``read`` returns the event as a StopRequest (stop_requests.py) and the loop applies it
   before update(): ``manager.emergency_stop(cause)``, or ``failproof_stop`` for a failed
   bus (a smart stop needs every joint). In update() the manager switches OK -> EMERGENCY:
   the emergency controller's initialize_fast and advance write this cycle's command (after
   the manager had ``neutral_command`` reset it), so the failed controller never commands
   again.
4. A second fault (another drive, or the emergency controller failing) -> FAILPROOF
   (``ControllerManager._estop``).
5. While the manager reports FAILPROOF, ``write`` sends the pre-encoded torque-off frames
   (frames_out.py: controlword 0x0000, mode, targets 0) for every drive in the same cycle,
   whatever JointCommand says. That path has no arithmetic and no branch that can raise; a
   send error is counted, never raised. A bug in the command path ends in the same frames.
   The failproof controller (TorqueOff) also zeroes JointCommand so loggers see the truth,
   but the frames do not depend on it.
6. If a controller hangs inside update(), the manager's watchdog thread
   (``rocoma_can.stopper.Watchdog``) calls ``send_torque_off`` every cycle until it
   returns: the pre-encoded frames and SYNC, no heartbeat. The hung advance then counts as
   a failure and the manager goes straight to FAILPROOF (the drives are off already).
7. If the loop itself dies or hangs, nothing is sent at all, including the manager
   heartbeat (produced by ``write``, never by a kernel BCM task that would outlive the
   process; the manager's CANopen node cannot start one either: node/server.py). Each
   drive's heartbeat consumer (0x1016, set at start-up by bringup.configure) times out and
   its abort connection option (0x6007 = 2, disable voltage) switches the power stage off.
   A consumer watches only after the first heartbeat it receives, so the start-up has
   one sent in the cycle a drive's configuration completes, before it can become READY.
   A node-guarded drive (no heartbeat, drive_plan.py) is the same with its life guarding:
   the guard requests (node_guarding.py) come from ``write`` only, from that cycle on.

Start-up (bringup/) never enables a drive; it ends in READY (torque off). Drives are enabled
step by step from the cyclic controlword (command.py, enable.py) only while the manager is OK
or EMERGENCY and the active layer commands a cyclic mode for them. Recovery (``recover``,
recovery.py) resets or restarts latched and failed drives over the following cycles.

This is everything software over CAN can do, and it is not a certified safe torque off: a
bus-off, a babbling node or firmware that ignores the controlword defeats it. Hard-wired STO
inputs or CANopen Safety (SRDO) are needed for that (docs/safety.md). That page
points here for these steps instead of keeping a second copy.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future

import can
import numpy as np

from ..errors import HomingFailed
from ..events import ManagerState
from .bringup.drive_bringup import BringupPhase, DriveBringup, create_bringups
from .bringup.start_up import StartUp
from .cycle.command import Commands
from .cycle.drive_table import raw_values, wire_drives
from .cycle.enable import EnableSequence
from .cycle.frames_out import FramesOut
from .cycle.node_guarding import NodeGuarding
from .cycle.receive import Receiver
from .cycle.recovery import Recovery
from .cycle.status import DriveStatus, HardwareStatus, bus_status, drive_status, recovery_status
from .cycle.status import not_ready as _not_ready
from .cycle.stop_requests import CycleFinding, ReadFindings
from .cycle.supervision import FaultEvent, Supervisor
from .link.bus_port import Bus, SentFrames, named_buses, open_ports
from .plan.config import DriveConfig, Supervision
from .plan.drive_clashes import check_drives, estop_conflict
from .plan.drive_plan import check_pdo_bytes, notes_with_drives, pdo_using, plan_drives
from .plan.pdo_layout import DriveLayout, cob_id_clashes
from .plan.scaling import Scaling
from .protocol import cia301
from .protocol.cia402 import State402
from .protocol.joints import JointCommand, JointState

__all__ = ["CanopenHardware", "DriveStatus", "HardwareStatus"]

log = logging.getLogger(__name__)


class CanopenHardware:
    """CiA 402 drives on one or several CAN buses, cycled by the control loop.

    ``bus``: one bus (a python-can bus lent by the caller, or a BusConfig opened by
    ``start``), or a mapping from bus name to bus for several; each drive names its bus in
    ``DriveConfig.bus`` ("" = the first). One JointState / JointCommand covers every joint.
    """

    def __init__(self, bus: Bus | Mapping[str, Bus], drives: Sequence[DriveConfig],
                 manager_node_id: int, dt: float, *,
                 manager_heartbeat_ms: int = 100, supervision: Supervision | None = None,
                 config_workers: int = 4, estop_cob_id: int = 0,
                 on_fault: Callable[[FaultEvent], None] | None = None) -> None:
        if not dt > 0:
            raise ValueError(f"dt must be a positive time step in seconds, got {dt!r}")
        buses = named_buses(bus)
        check_drives(list(drives), manager_node_id, list(buses))
        # each drive measured against its EDS/DCF: modes, feedback, PDOs, manager loss (the
        # axes of a multi-axis node share its PDO channels out), its limits at this rate
        self.plans = plan_drives(list(drives), next(iter(buses)), period=float(dt))
        drives = [p.drive for p in self.plans]
        clashes = cob_id_clashes([(p.drive, p.layout) for p in self.plans], manager_node_id,
                                 estop_cob_id, next(iter(buses)))
        if clashes:
            raise ValueError("; ".join(clashes))
        for note, which in notes_with_drives(self.plans):  # each said once, for every drive
            log.warning("%s: %s", which, note)
        supervision = supervision or Supervision()
        self.drives_config = drives
        self.manager_node_id = manager_node_id
        self.dt = float(dt)
        self.manager_heartbeat_period = manager_heartbeat_ms / 1000.0
        self.consumer_ms = supervision.consumer_ms(manager_heartbeat_ms)
        self.supervision = supervision
        self.timeouts = supervision.timeouts
        self.config_workers = max(1, int(config_workers))
        self.ports, self._table = wire_drives(self.plans, buses, manager_node_id)
        table = self._table
        check_pdo_bytes(drives, [(d.port.name, d.port.fd) for d in table])
        names = [d.name for d in drives]
        self.state = JointState.zeros(names)
        self.command = JointCommand.zeros(names)
        self.layouts: list[DriveLayout] = [p.layout for p in self.plans]
        self.scaling = Scaling(drives)
        self._raw = raw_values(len(drives))
        self.frames = FramesOut(table, ports=self.ports,
                                heartbeat_period=self.manager_heartbeat_period)
        self.guarding = NodeGuarding([p.guarded and p.leads_node for p in self.plans],
                                     [d.node_id for d in drives],
                                     [d.heartbeat_ms / 1000.0 for d in drives],
                                     [d.port for d in table])
        self.supervisor = Supervisor(
            drives, supervision.tpdo_timeout_cycles, supervision.heartbeat_timeout_factor,
            guarded=[p.guarded for p in self.plans],
            # a guarded node's loss says of every axis what its lead's answers were
            why_lost=lambda i: self.guarding.why_lost(table[i].node[0]))
        self.findings = ReadFindings(self.supervisor, on_fault)
        self.receiver = Receiver(table, ports=self.ports, raw=self._raw, state=self.state,
                                 scaling=self.scaling, supervisor=self.supervisor,
                                 guarding=self.guarding, on_estops=self.findings.estops,
                                 on_bus_off=self.findings.bus_failed)
        self.enable = EnableSequence(len(drives), self.timeouts.enable, self.supervisor.fault,
                                     min_cycles=supervision.tpdo_timeout_cycles)
        self.commands = Commands(table, state=self.state, command=self.command, raw=self._raw,
                                 scaling=self.scaling, supervisor=self.supervisor,
                                 enable=self.enable, frames=self.frames,
                                 ready=lambda: self.ready)
        self.recovery = Recovery(table, ports=self.ports, supervisor=self.supervisor,
                                 hb_state=self.receiver.hb_state,
                                 hb_time=self.receiver.hb_time,
                                 error_code=self.state.error_code)
        self._estop_cob_id = 0
        self.set_estop_cob_id(estop_cob_id)
        self._manager_state = ManagerState.FAILPROOF  # as of the last write
        self._started = False
        self._recorded: list[tuple[can.Listener, SentFrames]] = []
        # (hold_wakeups, release_wakeups) of every bus, taken by start (write wraps in them)
        self._wake_holds: list[tuple[Callable[[], None], Callable[[], None]]] = []
        # the bus readers' drain_now (start): read hands over what waits on the buses first
        self._drains: list[Callable[[], bool]] = []
        self._bringup: Sequence[DriveBringup] = ()
        self._start_up = StartUp([d.node_id for d in drives],
                                 [self.ports.index(d.port) for d in table],
                                 lambda bus: self.ports[bus].channel,
                                 on_ready=self._brought_up, on_configured=self._configured)
        self._now = 0.0
        self.fault_events = self.supervisor.history
        self.internal_errors = 0  # bugs caught in the cycle (each ended in torque-off frames)
        self.cycles = 0

    # --- life cycle ---------------------------------------------------------------------------
    def record_frames(self, taps: Sequence[tuple[can.Listener, SentFrames]]) -> None:
        """Before ``start``: per port, in order, where its received and sent frames are
        recorded (BusPort.record_frames)."""
        if len(taps) != len(self.ports):
            raise ValueError(f"{len(taps)} frame recorders for {len(self.ports)} buses")
        self._recorded = list(taps)

    def start(self, now: float | None = None) -> None:
        """Open the buses (unless lent), attach the receivers, begin every drive's bring-up.
        A bus that cannot be opened closes the ones opened before it and raises OSError."""
        if self._started:
            raise RuntimeError("CanopenHardware.start() called twice")
        self._started = True
        now = time.monotonic() if now is None else now
        self._wake_holds, self._drains = open_ports(
            self.ports, [self.receiver.cob_ids(k) for k in range(len(self.ports))],
            self._estop_cob_id, self._recorded)
        self.findings.switch_off.start()
        self._start_up.open_workers(min(self.config_workers, len(self.drives_config)))
        bringup = create_bringups(self.plans, [d.port.canopen for d in self._table],
                                  [d.node for d in self._table], self.manager_node_id,
                                  self.consumer_ms, self.dt, self.supervision)
        self._start_up.begin(bringup, now)
        self._now = now
        # published whole: a status read from another thread never sees half a list
        self._bringup = bringup
        self.receiver.attach_bringups(bringup)
        self.recovery.attach_bringups(bringup)
        self.findings.attach_bringups(bringup)

    def close(self) -> None:
        """Join the configuration workers and the bus reader; shut the bus if opened here."""
        self._start_up.close()
        self.findings.switch_off.close()
        for port in self.ports:
            port.close()
        self.recovery.close()

    def __enter__(self) -> CanopenHardware:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the cycle ------------------------------------------------------------------------------
    def read(self, now: float) -> Sequence[CycleFinding]:
        """Drain frames into JointState, step bring-up and recovery, supervise; what the
        manager must act on before this cycle's update, in the order found (the list is
        this hardware's own, valid until the next read). First the buses are read on this
        thread (BusReader.drain_now): the cycle sees what arrived before it, however late
        the scheduler runs the reader thread."""
        for drain in self._drains:
            drain()
        self._now = now
        findings = self.findings
        events = findings.begin()
        self.receiver.drain(now)
        self._start_up.step(now, self.receiver.complete, self.state.cia402_state,
                            self.state.error_code)
        sup = self.supervisor
        sup.tick(now, self.receiver.complete, self.state.cia402_state, self.state.error_code,
                 self.receiver.heard_until)
        recovered = self.recovery.step(now)
        if recovered is not None:
            findings.recovered(recovered)
        findings.deliver(sup.take_pending())
        self.cycles += 1
        return events

    def _brought_up(self, i: int, now: float) -> None:
        """Drive i became READY: supervised from now."""
        self.supervisor.arm(i, now)
        self.state.error_code[i] = 0

    def _configured(self, i: int) -> None:
        """Drive i's heartbeat consumer was just (re)configured, and it only starts watching
        with the first heartbeat it receives: one goes out in this cycle, so the drive is
        protected before it can become READY (a TPDO round trip later). Life guarding
        likewise starts with the first guard request."""
        self.frames.next_heartbeat = -math.inf
        self.guarding.start(i)

    def write(self, manager_state: ManagerState, switch_count: int | None = None) -> None:
        """Command frames (or torque-off frames in FAILPROOF), then SYNC, then heartbeat.
        ``switch_count``: the manager's committed switches, which arm the drives READY at
        that moment (None: no manager; every READY drive is under command).
        The readers of every bus are woken once, after all of it (BusPort.hold_wakeups):
        an in-process simulator then sees each bus's cycle whole and steps every segment's
        joints together, instead of waking at the first frame and taking the GIL from
        this write."""
        holds = self._wake_holds
        for hold, _ in holds:
            hold()
        try:
            self._write(manager_state, switch_count)
        finally:
            for _, release in holds:
                release()

    def _write(self, manager_state: ManagerState, switch_count: int | None) -> None:
        self._manager_state = manager_state
        commands = self.commands
        if manager_state != ManagerState.OK and commands.homing.busy:  # an e-stop ends
            for i in commands.homing.end_all(f"the manager left OK ({manager_state.name})"):
                commands.disarm(i)  # homing, queued jobs too; off until the next switch
        if manager_state == ManagerState.FAILPROOF:
            self._torque_off()
        else:
            try:
                commands.send(self._bringup, self._now, switch_count)
            except Exception:  # a bug here must still end in torque-off
                self.internal_errors += 1
                self._torque_off()
        self.frames.sync_and_heartbeat(self._now)
        if self._now >= self.guarding.next_due:
            self.guarding.send_due(self._now)
        self.findings.end_of_write(self.ports, self._now)

    def _torque_off(self) -> None:
        """FAILPROOF: the pre-encoded frames to every configured drive (frames_out.py)."""
        self.frames.torque_off(self._bringup)
        for i in range(len(self._bringup)):
            self.commands.reset(i)

    def send_torque_off(self) -> None:
        """Torque-off frames to every configured drive, then SYNC, from any thread.

        The manager's hang watchdog calls this while update() is stuck in a controller (the
        cycle sends nothing then). It only sends pre-encoded frames and touches no cycle
        state; it sends no heartbeat, so the drives' own heartbeat consumers still time out
        if the loop never comes back.
        """
        self.frames.watchdog_torque_off(self._bringup)

    # --- the manager's checks on JointCommand (command.py) ---------------------------------------
    def limit_command(self, command: JointCommand) -> bool:
        return self.commands.limit_command(command)

    def neutral_command(self, command: JointCommand) -> None:
        self.commands.neutral_command(command)

    # --- services: homing, recovery, e-stop frame -----------------------------------------------
    def home(self, drive: str, timeout: float | None = None, *,
             manager_state: ManagerState | None = None) -> Future[str]:
        """Home one drive (CiA 402 mode 6, its own method) over the following cycles, while
        the active controller keeps the others (homing.py). From any thread.

        Raises HomingFailed at once when the drive cannot be homed now (unknown, no homing
        mode in its 0x6502, no 0x6060 in its RPDO, not READY, faulted, already homing, the
        manager not OK); the future then says how it ended ("NAME: homed", or HomingFailed).
        ``manager_state``: the manager's own (runtime.system passes it): a switch that
        has just committed is OK before the next write tells this layer. Without it, the
        state of the last write counts. Should the manager leave OK before the job starts,
        the write fails it."""
        names = [d.name for d in self.drives_config]
        if drive not in names:
            raise HomingFailed(f"no drive named {drive!r} (drives: {', '.join(names)})")
        i = names.index(drive)
        return self.commands.homing.request(
            self._table[i], self._bringup[i].phase if self._bringup else None,
            self.supervisor.latched[i],
            (self._manager_state if manager_state is None else manager_state)
            == ManagerState.OK, timeout)

    def recover(self, timeout: float = 5.0) -> Future[bool]:
        """Fault reset / restart every faulted or failed drive; Future[bool] says if all came
        back (recovery.py). Runs over the following cycles (never blocks the caller's thread
        or the cycle). On success the latched faults are cleared and the loop clears the
        manager's e-stop latch (recovery.RecoveryDone): switching is allowed again. The
        future is resolved on the cycle thread, so a done-callback must be trivial."""
        return self.recovery.request(timeout)

    @property
    def estop_cob_id(self) -> int:
        return self._estop_cob_id

    def estop_conflict(self, cob_id: int) -> str | None:
        """Why ``cob_id`` cannot be the e-stop frame's on these buses, or None: a reserved
        id, or one a drive or the manager's own node uses (an e-stop taken for a drive's
        frame, or a drive's frame taken for an e-stop, would both be wrong)."""
        return (estop_conflict(cob_id, self.drives_config, self.manager_node_id)
                or pdo_using(cob_id, self.plans))

    def set_estop_cob_id(self, cob_id: int) -> None:
        """The e-stop frame's COB-ID on every bus (0 = off), from any thread: the manager
        node calls it when 0x2130 is written. ValueError for an id that is not free."""
        if not cia301.is_cob_id(cob_id):
            raise ValueError(f"estop_cob_id must be 0 (off) or an 11-bit COB-ID, got {cob_id!r}")
        why = self.estop_conflict(cob_id) if cob_id else None
        if why is not None:
            raise ValueError(f"estop_cob_id 0x{cob_id:03X} is {why}")
        self._estop_cob_id = self.receiver.estop_cob_id = cob_id
        for port in self.ports:
            port.set_estop_cob_id(cob_id)

    # --- status (status.py) ----------------------------------------------------------------------
    @property
    def bus_fault(self) -> str | None:
        """The latched bus faults (bus-off, frames refused), None when there is none."""
        causes = [p.latched for p in self.ports if p.latched is not None]
        return "; ".join(causes) if causes else None

    @property
    def tx_errors(self) -> int:
        """Frames the buses refused (counted, never raised)."""
        return sum(p.tx_errors for p in self.ports)

    @property
    def last_tx_error(self) -> Exception | None:
        errors = [p.last_tx_error for p in self.ports if p.last_tx_error is not None]
        return errors[-1] if errors else None

    @property
    def error_frames(self) -> int:
        """CAN error frames received on every bus (bus-off ones are a fault)."""
        return sum(p.error_frames for p in self.ports)

    @property
    def estop_frames(self) -> int:
        """E-stop frames received (any bus)."""
        return self.findings.estop_frames

    @property
    def hook_errors(self) -> int:
        """``on_fault`` calls that raised (counted, never raised)."""
        return self.findings.hook_errors

    @property
    def rx_bad(self) -> int:
        """TPDOs with a length other than their mapping's (never decoded)."""
        return self.receiver.rx_bad

    @property
    def guard_repeats(self) -> int:
        """Guard answers whose toggle bit did not change (not taken as a sign of life)."""
        return self.guarding.repeats

    @property
    def frames_per_cycle(self) -> int:
        """RPDOs + TPDOs of every drive + 1 SYNC per bus (the manager heartbeat is not per
        cycle)."""
        return sum(lay.frames_per_cycle for lay in self.layouts) + len(self.ports)

    @property
    def ready(self) -> np.ndarray:
        """Per drive: brought up, no latched fault (torque off until a controller enables it)."""
        return np.array([b.phase == BringupPhase.READY and self.supervisor.latched[i] is None
                         for i, b in enumerate(self._bringup)], dtype=bool)

    @property
    def all_ready(self) -> bool:
        return bool(self._bringup) and bool(self.ready.all())

    @property
    def started_up(self) -> bool:
        """The start-up has ended (every drive READY or FAILED once); a recovery that
        restarts drives later does not undo it."""
        return self._start_up.report.finished

    @property
    def starting(self) -> bool:
        """Some drive is still in bring-up (neither READY nor FAILED)."""
        return self._start_up.starting

    @property
    def enabled(self) -> np.ndarray:
        enabled: np.ndarray = self.ready & (self.state.cia402_state
                                            == State402.OPERATION_ENABLED)
        return enabled

    @property
    def all_enabled(self) -> bool:
        return bool(self._bringup) and bool(self.enabled.all())

    def not_ready(self, required: Sequence[int] | None = None) -> str | None:
        """Why the drives cannot be commanded now, or None (the manager's switch guard).
        ``required``: indices of the drives that must be ready (default: every drive)."""
        return _not_ready(self.drives_config, self._bringup, self.supervisor,
                          self.recovery.running, required)

    def drive_status(self) -> list[DriveStatus]:
        """A snapshot (from any thread: it only reads), one entry per configured drive."""
        enabled = self.enabled if self._bringup else np.zeros(len(self.drives_config), bool)
        return drive_status(self.drives_config, self._bringup, self.supervisor, self.state,
                            enabled, self.receiver.hb_state, self.receiver.hb_time,
                            self.commands.homing.seen)

    def status_report(self) -> HardwareStatus:
        """Whether start-up has finished, what a recovery is doing, every bus and drive."""
        drives = self.drive_status()
        return HardwareStatus(bool(self._bringup) and not self.starting,
                              recovery_status(self.recovery.future, drives), self.bus_fault,
                              bus_status(self.ports), drives)
