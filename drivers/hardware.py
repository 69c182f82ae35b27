"""The CAN hardware layer: N CiA 402 drives as one JointState / JointCommand pair.

One cycle, on the one thread that owns the loop (``run_cycle`` does exactly this)::

    hw.read(now)       drain received frames -> JointState; bring-up steps; supervision
    manager.update()   the active layer writes JointCommand
    hw.write(state)    RPDOs (or torque-off frames) for every drive, SYNC, manager heartbeat,
                       guard requests to node-guarded drives

The safety path, top to bottom (each step names where it lives):

1. A drive goes wrong. Supervision (supervision.py) turns every symptom into a FaultEvent:
   EMCY, statusword fault bit, heartbeat (or node guarding answer) deadline or a non-
   operational state in it, TPDOs missing
   for k cycles, a drive dropping out of operation enabled or not enabling in time
   (``_command_frames`` below). A whole bus can fail too: a bus-off error frame or the bus
   refusing frames in ``tpdo_timeout_cycles`` cycles in a row (``BusPort.bus_off`` and
   ``BusPort.end_of_write``, bus_port.py) is a fault of every drive on it (``_bus_failed``).
   Frames arrive on the buses' reader thread (bus.py: one for all buses where the
   interface allows, else one per bus), which only appends them to each bus's deque;
   ``read`` drains every bus on the cycle thread, so no lock is shared with a slow thread.
   ``read`` first reads the buses itself where the reader thread is not reading
   (BusReader.drain_now, a lock only tried): a starved reader thread delays nothing.
   An e-stop frame (``estop_cob_id``, any bus) is drained the same way (``_on_estop_frames``)
   and reaches the manager before this cycle's update.
2. The faulted drive gets torque-off frames from the same cycle on (``_command_frames``:
   a latched drive is never sent anything but controlword 0x0000), until recovery, and
   controlword 0x0000 once by SDO from a thread of its own (``_deliver``, switch_off.py): a
   drive that no longer applies RPDOs (pre-operational, ignoring SYNC) still switches off.
3. ``read`` hands the event to the manager before update(): ``manager.emergency_stop(cause)``
   (``_deliver``; ``rocoma_can.runtime.system.manager_for`` wires it), or
   ``failproof_stop`` for a failed bus (a smart stop needs every joint). In update() the
   manager switches OK -> EMERGENCY: the emergency controller's initialize_fast and advance
   write this cycle's command (after the manager's ``_estop`` had ``neutral_command``
   reset it), so the failed controller never commands again.
4. A second fault (another drive, or the emergency controller failing) -> FAILPROOF
   (``ControllerManager._estop``).
5. While the manager reports FAILPROOF, ``write`` sends the pre-encoded torque-off frames
   (controlword 0x0000, mode, targets 0; built in ``__init__``) for every drive in the same
   cycle, whatever JointCommand says. That path has no arithmetic and no branch that can
   raise; a send error is counted, never raised. The failproof controller (TorqueOff) also
   zeroes JointCommand so loggers see the truth, but the frames do not depend on it.
6. If a controller hangs inside update(), the manager's watchdog thread
   (``rocoma_can.stopper.Watchdog``) calls ``send_torque_off`` every cycle until it
   returns: the pre-encoded frames and SYNC, no heartbeat. The hung advance then counts as a
   failure and the manager goes straight to FAILPROOF (the drives are off already).
7. If the loop itself dies or hangs, nothing is sent at all, including the manager
   heartbeat (produced by ``write``, never by a kernel BCM task that would outlive the
   process; the manager's CANopen node cannot start one either: node/server.py). Each
   drive's heartbeat consumer (0x1016, set at start-up by bringup.configure) times out and
   its abort connection option (0x6007 = 2, disable voltage) switches the power stage off.
   A consumer watches only after the first heartbeat it receives, so ``_step_bringup`` has
   one sent in the cycle a drive's configuration completes, before it can become READY.
   A node-guarded drive (no heartbeat, drive_plan.py) is the same with its life guarding:
   the guard requests (``_guard``) come from ``write`` only, from that cycle on.

Start-up (bringup.py) never enables a drive; it ends in READY (torque off). Drives are enabled
step by step from the cyclic controlword (``_command_frames``, enable.py) only while the
manager is OK or EMERGENCY and the active layer commands a cyclic mode for them. Recovery
(``recover``) resets or restarts latched and failed drives over the following cycles.

This is everything software over CAN can do, and it is not a certified safe torque off: a
bus-off, a babbling node or firmware that ignores the controlword defeats it. Hard-wired STO
inputs or CANopen Safety (SRDO) are needed for that (docs/safety.md). That page
points here for these steps instead of keeping a second copy.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

import can
import numpy as np

from ..errors import HomingFailed
from ..events import ManagerState
from . import cia301, cia402
from .bringup import DriveBringup, Phase
from .bus import start_reading
from .bus_port import BusPort
from .cia402 import State402
from .config import BusConfig, DriveConfig, Supervision, check_drives, estop_conflict
from .drive_plan import plan_drives
from .enable import OP_ENABLED, EnableSequence
from .frame_io import clock_offset, to_monotonic
from .homing import HOMING_MODE, HomingJob
from .joints import JointCommand, JointMode, JointState
from .modes import CW_ENABLE_INTERPOLATION, KIND, DriveMode, SetPointHandshake, carrier
from .pdo_layout import IGNORED, DriveLayout, cob_id_clashes
from .scaling import Scaling
from .supervision import FaultEvent, Supervisor
from .switch_off import SdoSwitchOff

_CW_FAULT_RESET = int(cia402.Controlword.FAULT_RESET)
_CW_QUICK_STOP = int(cia402.Controlword.QUICK_STOP)
_CYCLIC = (int(JointMode.CSP), int(JointMode.CSV), int(JointMode.CST))
_PP, _IP = int(DriveMode.PP), int(DriveMode.IP)


@dataclass(frozen=True)
class DriveStatus:
    """A snapshot for status reports and services."""
    name: str
    node_id: int
    phase: str            # a bringup.Phase name: WAIT_BOOT ... READY, FAILED
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


def _reported(value: float, mapped: bool) -> float | None:
    """A feedback value for a status report: None when the drive does not report it (or it
    is not a number: JSON has no NaN)."""
    v = float(value)
    return round(v, 5) if mapped and math.isfinite(v) else None


class Manager(Protocol):
    """What the hardware needs of the manager it is attached to (rocoma_can's
    ControllerManager): nothing in drivers/ builds or imports one."""
    switch_count: int

    @property
    def state(self) -> ManagerState: ...
    def update(self) -> ManagerState: ...
    def post_cycle(self) -> None: ...
    def emergency_stop(self, cause: str = ...) -> None: ...
    def failproof_stop(self, cause: str = ...) -> None: ...
    def clear_emergency_stop(self) -> bool: ...


Bus = can.BusABC | BusConfig
#: A TPDO's receive entry: drive index, its bit in the cycle's mask, size, unpack, targets
log = logging.getLogger(__name__)
#: how long start() waits for the configuration workers' threads to run
WORKER_START = 5.0

_TpdoEntry = tuple[int, int, int, Callable[..., tuple[int, ...]], tuple[np.ndarray, ...]]


def _whole_cob_id(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 0x7FF


def _named_buses(bus: Bus | Mapping[str, Bus]) -> dict[str, Bus]:
    """One bus (named by its config, or "bus" when lent) or a name -> bus mapping."""
    if isinstance(bus, Mapping):
        if not bus:
            raise ValueError("buses: at least one bus is needed")
        return dict(bus)
    return {bus.label if isinstance(bus, BusConfig) else "bus": bus}


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
        buses = _named_buses(bus)
        check_drives(list(drives), manager_node_id, list(buses))
        # each drive measured against its EDS/DCF: modes, feedback, PDOs, manager loss (the
        # axes of a multi-axis node share its PDO channels out)
        self.plans = plan_drives(list(drives), next(iter(buses)))
        drives = [p.drive for p in self.plans]
        clashes = cob_id_clashes([(p.drive, p.layout) for p in self.plans], manager_node_id,
                                 estop_cob_id, next(iter(buses)))
        if clashes:
            raise ValueError("; ".join(clashes))
        for p in self.plans:
            for note in p.notes:
                log.warning("drive %r: %s", p.drive.name, note)
        supervision = supervision or Supervision()
        if not dt > 0:
            raise ValueError(f"dt must be a positive time step in seconds, got {dt!r}")
        consumer_ms = int(round(manager_heartbeat_ms * supervision.consumer_factor))
        if not 1 <= manager_heartbeat_ms or consumer_ms > 0xFFFF:
            raise ValueError("manager_heartbeat_ms must be >= 1 and its product with "
                             "supervision.consumer_factor <= 65535 ms (the drives' heartbeat "
                             f"consumer time); got {manager_heartbeat_ms} and "
                             f"{supervision.consumer_factor}")
        self.drives_config = drives
        self.manager_node_id = manager_node_id
        self.dt = float(dt)
        self.manager_heartbeat_period = manager_heartbeat_ms / 1000.0
        self.consumer_ms = consumer_ms
        self.supervision = supervision
        self.timeouts = supervision.timeouts
        self.config_workers = max(1, int(config_workers))
        self.on_fault = on_fault
        n = len(drives)
        first = next(iter(buses))
        self.ports = [BusPort(name, arg, [i for i, d in enumerate(drives)
                                          if (d.bus or first) == name], manager_node_id)
                      for name, arg in buses.items()]
        port_of = {p.name: p for p in self.ports}
        self._port_of = [port_of[d.bus or first] for d in drives]
        self._estop_cob_id = 0
        self.set_estop_cob_id(estop_cob_id)
        self.estop_frames = 0  # e-stop frames received (any bus)
        names = [d.name for d in drives]
        self.state = JointState.zeros(names)
        self.command = JointCommand.zeros(names)
        self.layouts: list[DriveLayout] = [p.layout for p in self.plans]
        self.scaling = Scaling(drives)
        self.supervisor = Supervisor(drives, supervision.tpdo_timeout_cycles,
                                     supervision.heartbeat_timeout_factor,
                                     guarded=[p.guarded for p in self.plans])

        # --- raw bus values, one slot per drive (the codecs read and write these) ---------
        self._raw = {name: np.zeros(n, dtype=np.int64) for name in
                     ("statusword", "position", "velocity", "torque",
                      "target_position", "target_velocity", "target_torque", IGNORED)}
        self._allowed_modes = np.array(
            [(1 << JointMode.TORQUE_OFF) | (1 << JointMode.QUICK_STOP)
             | sum(1 << int(KIND[m]) for m in d.modes) for d in drives], dtype=np.int64)
        # the 0x6060 value that carries each commanded JointMode, per drive (modes.py)
        self._carrier = [carrier(d.modes) for d in drives]
        self._setpoints = SetPointHandshake(n)  # PP drives' set-point handshake
        # homing (homing.py): requests from any thread, taken by the cycle
        self._homing: list[HomingJob | None] = [None] * n
        self._homing_requests: collections.deque[HomingJob] = collections.deque()
        self._homing_seen: list[HomingJob | None] = [None] * n  # the last job, for status
        self._homing_lock = threading.Lock()
        self._pp = [DriveMode.PP in d.modes for d in drives]  # the set-point handshake
        self._allowed_list = self._allowed_modes.tolist()
        self._mode_bits = np.zeros(n, dtype=np.int64)
        self._ones = np.ones(n, dtype=np.int64)
        self._finite = np.zeros(n, dtype=bool)
        self._position_fed = np.array([lay.maps("position") for lay in self.layouts],
                                      dtype=bool)
        self._default_mode = [int(d.modes[0]) for d in drives]
        self._got = np.zeros(n, dtype=np.int64)             # TPDO bits seen this cycle
        # one bit per TPDO slot a drive's layout uses (a fixed mapping may use TPDO3 and 4)
        self._expected = np.array([sum(1 << (p.number - 1) for p in lay.tpdos)
                                   for lay in self.layouts],
                                  dtype=np.int64)
        self._complete = np.zeros(n, dtype=bool)
        self.enable = EnableSequence(n, supervision.timeouts.enable, self.supervisor.fault,
                                     min_cycles=supervision.tpdo_timeout_cycles)
        # The drives the active controller may command: those ready when its switch was
        # committed. A drive ready only later (recovered, late start) stays torque-off
        # until the next switch: that controller never saw it (its pose, its limits).
        self._armed = [False] * n
        self._switches_seen = -1
        self._hb_state = [-1] * n
        self._hb_time = np.full(n, -math.inf)
        # the drives of each drive's node (several: the axes of a multi-axis device, which
        # share its NMT state, heartbeat or guarding, EMCY and SDO server), lowest axis first
        node_of: dict[tuple[str, int], list[int]] = {}
        for i, d in enumerate(drives):
            node_of.setdefault((self._port_of[i].name, d.node_id), []).append(i)
        self._node = [tuple(sorted(node_of[self._port_of[i].name, d.node_id],
                                   key=lambda k: drives[k].axis)) for i, d in enumerate(drives)]
        # per drive: its bus's reader had handed over every frame that arrived before this
        # when the cycle began draining (heartbeat deadlines are judged against it, below)
        self._heard_until = np.full(n, -math.inf)
        self._drives_of_port = [np.array(port.drives, dtype=np.intp) for port in self.ports]

        # --- receive tables per bus: COB-ID -> what to do with the frame -------------------
        self._tpdo_of: list[dict[int, _TpdoEntry]] = [{} for _ in self.ports]
        for k, port in enumerate(self.ports):
            for i in port.drives:
                d = drives[i]
                for pdo in self.layouts[i].tpdos:
                    self._tpdo_of[k][pdo.cob_id] = (
                        i, 1 << (pdo.number - 1), pdo.size, pdo.codec.unpack_from,
                        tuple(self._raw[name] for name in pdo.names))
                if self.plans[i].leads_node:
                    port.heartbeat_of[cia301.HEARTBEAT + d.node_id] = i
                    port.emcy_of[cia301.EMCY + d.node_id] = self._node[i]

        # --- transmit frames, allocated once -------------------------------------------------
        # Per drive and RPDO: (frame, codec.pack_into, positions of its entries in the
        # drive's RPDO fields: RPDO_FIELDS, then the constants of a fixed mapping)
        self._rpdo_frames = [[(self._port_of[i].frame(p.cob_id, p.size), p.codec.pack_into,
                               p.positions_in(lay.rpdo_fields)) for p in lay.rpdos]
                             for i, lay in enumerate(self.layouts)]
        self._rpdo_constants = [lay.rpdo_constants for lay in self.layouts]
        self._send_of = [port.send for port in self._port_of]
        self._torque_off_frames = [self._preencode(i, 0) for i in range(n)]
        self._fault_reset_frames = [self._preencode(i, _CW_FAULT_RESET) for i in range(n)]
        self._probe_frames = [self._preencode(i, int(cia402.Controlword.SHUTDOWN))
                              for i in range(n)]
        self._next_heartbeat = -math.inf
        # node guarding (drives without a heartbeat, drive_plan): a remote request every
        # heartbeat_ms from the cycle, once the drive is configured; the answers come in
        # as heartbeats do, with a toggle bit that must change
        self._guarded = [p.guarded and p.leads_node for p in self.plans]  # once per node
        self._guarded_drives = [i for i in range(n) if self._guarded[i]]
        self._guard_frames = {i: can.Message(arbitration_id=cia301.HEARTBEAT
                                             + drives[i].node_id, is_remote_frame=True,
                                             dlc=1, is_extended_id=False)
                              for i in self._guarded_drives}
        self._guard_period = [d.heartbeat_ms / 1000.0 for d in drives]
        self._guard_due = [math.inf] * n         # inf: not guarded (yet)
        self._next_guard = math.inf              # the earliest of them
        self._toggle = [-1] * n                  # the last answer's toggle bit; -1: none yet
        self._asked = [0] * n                    # requests sent since the last answer taken
        self.guard_repeats = 0                   # answers whose toggle bit did not change
        self._manager_state = ManagerState.FAILPROOF  # as of the last write

        self._started = False
        # (hold_wakeups, release_wakeups) of every bus, taken by start (write wraps in them)
        self._wake_holds: list[tuple[Callable[[], None], Callable[[], None]]] = []
        # the bus readers' drain_now (start): read hands over what waits on the buses first
        self._drains: list[Callable[[], bool]] = []
        self._bringup: list[DriveBringup] = []
        self._executor: ThreadPoolExecutor | None = None
        self._switch_off = SdoSwitchOff()  # started with the bus (start)
        self._manager: Manager | None = None
        self._recovery: Future[bool] | None = None
        self._recovery_started = False
        self._recovery_timeout = 5.0
        self._recovery_deadline = math.inf
        self._now = 0.0
        self.fault_events: collections.deque[FaultEvent] = self.supervisor.history
        self.rx_bad = 0        # TPDOs with a length other than their mapping's (never decoded)
        self.internal_errors = 0  # bugs caught in the cycle (each ended in torque-off frames)
        self.hook_errors = 0   # on_fault calls that raised (counted, never raised)
        self.cycles = 0

    def _preencode(self, i: int, controlword: int) -> list[can.Message]:
        """Torque-off frames for drive i: controlword, the default mode, every target 0."""
        layout = self.layouts[i]
        values = (controlword, self._default_mode[i], 0, 0, 0, *layout.rpdo_constants)
        frames = []
        for pdo in layout.rpdos:
            msg = self._port_of[i].frame(pdo.cob_id, pdo.size)
            where = pdo.positions_in(layout.rpdo_fields)
            pdo.codec.pack_into(msg.data, 0, *(values[k] for k in where))
            frames.append(msg)
        return frames

    # --- life cycle ---------------------------------------------------------------------------
    def start(self, now: float | None = None) -> None:
        """Open the buses (unless lent), attach the receivers, begin every drive's bring-up.
        A bus that cannot be opened closes the ones opened before it and raises OSError."""
        if self._started:
            raise RuntimeError("CanopenHardware.start() called twice")
        self._started = True
        now = time.monotonic() if now is None else now
        try:
            for k, port in enumerate(self.ports):
                port.open(set(self._tpdo_of[k]) | set(port.heartbeat_of) | set(port.emcy_of))
                port.set_estop_cob_id(self._estop_cob_id)
            # one reader thread for every bus where the interface allows (bus.readers_for)
            start_reading([port.canopen for port in self.ports if port.canopen is not None])
            # the open buses' wake-up holds for write, as pairs: a port closed while a
            # write runs is still released by the bus it held
            self._wake_holds = [(port.hold_wakeups, port.release_wakeups)
                                for port in self.ports]
            readers = {id(port.canopen.reader): port.canopen.reader for port in self.ports
                       if port.canopen is not None and port.canopen.reader is not None}
            self._drains = [reader.drain_now for reader in readers.values()]
        except BaseException:
            for port in self.ports:
                port.close()
            raise
        self._switch_off = SdoSwitchOff()
        self._switch_off.start()
        workers = min(self.config_workers, len(self.drives_config))
        self._executor = ThreadPoolExecutor(max_workers=workers,
                                            thread_name_prefix="canopen-config")
        # Every worker started here: the executor starts one on a submit that finds none
        # idle, and bring-up submits from the cycle (read), which must not start a thread.
        # Each waits at the barrier, so each submit finds none idle and starts one.
        started = threading.Barrier(workers + 1)
        for _ in range(workers):
            self._executor.submit(started.wait, WORKER_START)
        try:
            started.wait(WORKER_START)
        except threading.BrokenBarrierError:  # a machine that slow starts the rest later
            log.warning("configuration workers not all started within %.0f s", WORKER_START)
        made: dict[int, DriveBringup] = {}
        # each node's lowest axis first: a higher axis shares its node's SDO client and lock
        for i in sorted(range(len(self.plans)), key=lambda k: self._node[k][0] != k):
            plan, port = self.plans[i], self._port_of[i]
            assert port.canopen is not None  # opened above
            lead = self._node[i][0]
            if lead != i:
                made[i] = DriveBringup(plan, made[lead].node, self.manager_node_id,
                                       self.consumer_ms, self.timeouts, self.dt,
                                       lead=made[lead])
                continue
            network = port.canopen.network
            node = network.add_node(plan.drive.node_id, plan.caps.object_dictionary)
            # The cycle decodes heartbeats and EMCYs itself (read): canopen's consumers of
            # them would only keep an EMCY log that grows for the whole run and log an
            # error per short frame a faulty drive sends.
            network.unsubscribe(cia301.HEARTBEAT + plan.drive.node_id, node.nmt.on_heartbeat)
            network.unsubscribe(cia301.EMCY + plan.drive.node_id, node.emcy.on_emcy)
            network.unsubscribe(cia301.NMT, node.nmt.on_command)
            # No retransmission by default (CiA 301 clients abort on timeout): a late answer
            # to the first copy would be taken as the answer to the next request. configure()
            # repeats a whole failed attempt instead, after stale answers have drained.
            node.sdo.RESPONSE_TIMEOUT = self.supervision.sdo_timeout
            # canopen counts tries (0 = forever)
            node.sdo.MAX_RETRIES = self.supervision.sdo_retries + 1
            made[i] = DriveBringup(plan, node, self.manager_node_id, self.consumer_ms,
                                   self.timeouts, self.dt)
        self._bringup = [made[i] for i in range(len(self.plans))]
        for b in self._bringup:
            b.restart(now)
        self._now = now

    def close(self) -> None:
        """Join the configuration workers and the bus reader; shut the bus if opened here."""
        for b in self._bringup:
            b.cancel()
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        self._switch_off.close()
        for port in self.ports:
            port.close()
        if self._recovery is not None and not self._recovery.done():
            self._recovery.set_result(False)

    def __enter__(self) -> CanopenHardware:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- manager wiring -------------------------------------------------------------------------
    def attach(self, manager: Manager) -> None:
        """Route fault events to ``manager.emergency_stop`` (before its update, from read)."""
        self._manager = manager

    def run_cycle(self, now: float | None = None) -> ManagerState:
        """read, manager.update, write, manager.post_cycle: one whole cycle (needs
        ``attach``, which ``rocoma_can.runtime.system.manager_for`` does)."""
        if self._manager is None:
            raise RuntimeError("run_cycle needs a manager: attach() one first")
        self.read(time.monotonic() if now is None else now)
        state = self._manager.update()
        self.write(state)
        self._manager.post_cycle()
        return state

    # --- the cycle ------------------------------------------------------------------------------
    def read(self, now: float) -> None:
        """Drain frames into JointState, step bring-up and recovery, raise fault events.
        First the buses are read on this thread (BusReader.drain_now): the cycle sees what
        arrived before it, however late the scheduler runs the reader thread."""
        for drain in self._drains:
            drain()
        self._now = now
        sup = self.supervisor
        got = self._got
        got.fill(0)
        stamp = self.state.stamp
        offset = clock_offset()
        estop, estops = self._estop_cob_id or -1, 0
        for k, port in enumerate(self.ports):
            rx = port.rx
            tpdo_of, heartbeat_of, emcy_of = self._tpdo_of[k], port.heartbeat_of, port.emcy_of
            # Before draining: every frame that arrived before ``until`` is in ``rx`` now.
            # A reader starved past a deadline (a frozen process) has heartbeats in time
            # still unread; the deadline waits for them (a dead reader judges on ``now``).
            cb = port.canopen
            reader = cb.reader if cb is not None else None
            until = now if cb is None or reader is None or not reader.alive else min(
                now, reader.received_until(cb.bus))
            self._heard_until[self._drives_of_port[k]] = until
            while rx:
                msg = rx.popleft()
                cob = msg.arbitration_id
                if cob == estop:  # first: an e-stop is never taken for anything else
                    estops += 1
                    continue
                t = to_monotonic(offset, msg.timestamp, now)
                entry = tpdo_of.get(cob)
                if entry is not None:
                    i, bit, size, unpack, targets = entry
                    if msg.dlc != size:  # not what we mapped: never decoded, a fault once armed
                        self.rx_bad += 1
                        sup.on_bad_tpdo(i, cob, msg.dlc, size, t)
                        continue
                    values = unpack(msg.data)
                    for arr, v in zip(targets, values):
                        arr[i] = v
                    got[i] |= bit
                    stamp[i] = t
                    continue
                beat = heartbeat_of.get(cob)
                if beat is not None:
                    if msg.dlc >= 1:
                        self._on_heartbeat(beat, msg.data[0], t)
                    continue
                axes = emcy_of.get(cob)
                if axes is not None and msg.dlc >= 2:
                    code = msg.data[0] | (msg.data[1] << 8)
                    for j in axes:
                        self.state.error_code[j] = code
                        if code == cia301.EMCY_STO:
                            self._bringup[j].sto_seen = True
                    # An EMCY does not say which axis of a multi-axis node it is about:
                    # there each axis is faulted by its own statusword, not by the EMCY
                    if len(axes) == 1:
                        sup.on_emcy(axes[0], code, t)
            if estops:
                self._on_estop_frames(port, estops)
                estops = 0
            if port.rx_errors:
                cause = port.bus_off()
                if cause is not None:
                    self._bus_failed(port, cause, now)
        np.equal(got, self._expected, out=self._complete)
        self._decode(now)
        self._step_bringup(now)
        sup.tick(now, self._complete, self.state.cia402_state, self.state.error_code,
                 self._heard_until)
        self._step_recovery(now)
        self._deliver(sup.take_pending())
        self.cycles += 1

    def _on_estop_frames(self, port: BusPort, count: int) -> None:
        """E-stop frames on one bus in this read: one request (a sender that repeats its
        frame must not cost the cycle a request each); the manager's update, which runs
        right after this read, acts on it."""
        self.estop_frames += count
        if self._manager is not None:
            self._manager.emergency_stop(
                cause=f"CAN e-stop from 0x{self._estop_cob_id:03X} on bus {port.name!r}")

    def _bus_failed(self, port: BusPort, cause: str, now: float) -> None:
        """A fault of every drive on the bus and one event (Supervisor.bus_fault), latched
        on the port until recovery; ``_deliver`` makes it a failproof stop: an emergency
        controller written for the whole robot cannot stop it smartly with a bus of joints
        gone, so every other bus gets torque-off frames from this cycle on."""
        if port.latched is None:
            port.latched = cause
            self.supervisor.bus_fault(cause, now, port.drives, bus=port.name)

    def _on_heartbeat(self, i: int, nmt_state: int, t: float) -> None:
        if self._guarded[i]:  # a node guarding answer: toggle bit 7, the state below it
            toggle = nmt_state & cia301.GUARD_TOGGLE
            nmt_state &= ~cia301.GUARD_TOGGLE
            if nmt_state == cia301.NmtState.BOOT_UP:  # a boot-up restarts the toggling
                self._toggle[i] = -1
            elif toggle == self._toggle[i] and self._asked[i] < 2:
                # the answer taken last, again (a stale or doubled frame): it does not
                # count (answers that never toggle run into the deadline, a guarding loss).
                # After two requests or more the same bit is a new answer: the one between
                # was lost, and one lost frame is not a lost drive.
                self.guard_repeats += 1
                return
            else:
                self._toggle[i] = toggle
                self._asked[i] = 0
        for k in self._node[i]:  # every axis of the node: its NMT state is theirs
            self._hb_state[k] = nmt_state
            self._hb_time[k] = t
            self._bringup[k].alive = True
            self.supervisor.on_heartbeat(k, nmt_state, t)

    def _decode(self, now: float) -> None:
        s, raw, sc = self.state, self._raw, self.scaling
        np.copyto(s.fresh, self._complete)
        sc.decode(raw["position"], sc.position, s.position)
        sc.decode(raw["velocity"], sc.velocity, s.velocity)
        sc.decode(raw["torque"], sc.torque, s.torque)
        np.copyto(s.statusword, raw["statusword"], casting="unsafe")
        cia402.states_from_statuswords(s.statusword, s.cia402_state)
        s.time = now

    def _step_bringup(self, now: float) -> None:
        executor = self._executor
        if executor is None:
            return
        states, fresh, codes = self.state.cia402_state, self._complete, self.state.error_code
        for i, b in enumerate(self._bringup):
            phase = b.phase
            if phase == Phase.READY or phase == Phase.FAILED:
                continue
            if b.step(now, executor, bool(fresh[i]), int(states[i]), int(codes[i])):
                self.supervisor.arm(i, now)
                self.state.error_code[i] = 0
            elif b.phase == Phase.FAILED:
                # said once, at once, on stderr (status has it too); written by a worker:
                # the cycle does no I/O
                executor.submit(log.error, "drive %r (node %d): start-up failed: %s", b.name,
                                b.drive.node_id, b.failure)
            elif phase == Phase.CONFIGURING and b.phase == Phase.STARTING:
                # The drive's heartbeat consumer was just (re)configured, and it only starts
                # watching with the first heartbeat it receives: send one in this cycle, so
                # the drive is protected before it can become READY (a TPDO round trip later).
                # Life guarding likewise starts with the first guard request.
                self._next_heartbeat = -math.inf
                if self._guarded[i]:
                    self._guard_due[i] = self._next_guard = -math.inf

    def _still_latched(self, i: int, event: FaultEvent) -> Callable[[], bool]:
        """For the SDO switch-off: whether drive i is still latched by ``event``."""
        latched = self.supervisor.latched
        return lambda: latched[i] is event

    def _deliver(self, events: list[FaultEvent]) -> None:
        sup = self.supervisor
        for event in events:
            manager = self._manager
            if manager is not None:  # a deque append: cannot fail
                if event.index < 0:  # a whole bus: no smart stop without those joints
                    manager.failproof_stop(cause=str(event))
                else:
                    manager.emergency_stop(cause=str(event))
            i = event.index
            if (0 <= i < len(self._bringup) and self._bringup[i].mapped
                    and sup.latched[i] is event):  # a queue append: cannot block
                self._switch_off.request(self._bringup[i], self._still_latched(i, event))
            if self.on_fault is not None:
                try:
                    self.on_fault(event)
                except Exception:  # a reporting hook must not take the cycle down
                    self.hook_errors += 1

    def write(self, manager_state: ManagerState) -> None:
        """Command frames (or torque-off frames in FAILPROOF), then SYNC, then heartbeat.
        The readers of every bus are woken once, after all of it (BusPort.hold_wakeups):
        an in-process simulator then sees each bus's cycle whole and steps every segment's
        joints together, instead of waking at the first frame and taking the GIL from
        this write."""
        holds = self._wake_holds
        for hold, _ in holds:
            hold()
        try:
            self._write(manager_state)
        finally:
            for _, release in holds:
                release()

    def _write(self, manager_state: ManagerState) -> None:
        self._manager_state = manager_state
        if manager_state != ManagerState.OK:  # an e-stop ends homing, queued ones too
            while self._homing_requests:
                self._homing_requests.popleft().fail(
                    f"the manager left OK ({manager_state.name}) before homing started")
            for i, job in enumerate(self._homing):
                if job is not None:
                    job.fail(f"the manager left OK ({manager_state.name})")
                    self._homing[i] = None
                    self._armed[i] = False  # off until the next switch
        if manager_state == ManagerState.FAILPROOF:
            self._torque_off()
        else:
            try:
                self._command_frames()
            except Exception:  # a bug here must still end in torque-off
                self.internal_errors += 1
                self._torque_off()
        self._end_of_write()

    def _end_of_write(self) -> None:
        """SYNC, then the manager heartbeat when due, on every bus back to back; then each
        bus's transmit health. A bus that refuses frames cycle after cycle (transmit queue
        full, interface down) delivers no command and no heartbeat: after as many cycles as
        missing TPDOs are tolerated it is a bus fault, an e-stop like bus-off. A recovery
        succeeds only after as many cycles in a row without a refused frame on every bus."""
        ports = self.ports
        for port in ports:
            port.send(port.sync)
        if self._now >= self._next_heartbeat:
            for port in ports:
                port.send(port.heartbeat)
            # On the grid 0x1017 declares: due a period after the last due time, sent in the
            # first cycle at or after it (at most a cycle late, never late on average). From
            # the send time, every beat was late by the part of a cycle it waited, and those
            # added up (520 ms for 500 at 25 Hz). A grid a whole period behind (a stalled
            # loop, a beat sent out of turn) starts again from now: no burst of beats.
            due = self._next_heartbeat + self.manager_heartbeat_period
            self._next_heartbeat = (due if due > self._now
                                    else self._now + self.manager_heartbeat_period)
        if self._now >= self._next_guard:
            self._guard()
        limit = self.supervisor.tpdo_timeout_cycles
        for port in ports:
            cause = port.end_of_write(limit)
            if cause is not None:
                self._bus_failed(port, cause, self._now)

    def _guard(self) -> None:
        """The guard requests that are due, on the grid heartbeats use (``_end_of_write``).
        Like the manager's heartbeat they come from the cycle only: a loop that stops or
        hangs stops guarding, and each guarded drive's life guarding times out."""
        now, due, period, asked = self._now, self._guard_due, self._guard_period, self._asked
        nearest = math.inf
        for i in self._guarded_drives:
            if due[i] <= now:
                self._send_of[i](self._guard_frames[i])
                asked[i] += 1
                nxt = due[i] + period[i]
                due[i] = nxt if nxt > now else now + period[i]
            if due[i] < nearest:
                nearest = due[i]
        self._next_guard = nearest

    def _torque_off(self) -> None:
        """FAILPROOF: pre-encoded disable-voltage frames to every configured drive."""
        send_of = self._send_of
        for i, b in enumerate(self._bringup):
            if b.mapped:
                send = send_of[i]
                for msg in self._start_frames(i, b):
                    send(msg)
            self.enable.reset(i)
            if self._pp[i]:
                self._setpoints.reset(i)

    def send_torque_off(self) -> None:
        """Torque-off frames to every mapped drive, then SYNC, from any thread.

        The manager's hang watchdog calls this while update() is stuck in a controller (the
        cycle sends nothing then). It only sends pre-encoded frames and touches no cycle
        state; it sends no heartbeat, so the drives' own heartbeat consumers still time out
        if the loop never comes back.
        """
        send_of = self._send_of
        for i, b in enumerate(self._bringup):
            if b.mapped:
                send = send_of[i]
                for msg in self._torque_off_frames[i]:
                    send(msg)
        for port in self.ports:
            port.send(port.sync)

    def _start_frames(self, i: int, b: DriveBringup) -> list[can.Message]:
        """Pre-encoded frames for a drive not under command: torque off, or the fault-reset
        edge / shutdown probe of its bring-up (both keep the power stage off)."""
        if b.fault_reset_bit:
            return self._fault_reset_frames[i]
        if b.probing:
            return self._probe_frames[i]
        return self._torque_off_frames[i]

    def _command_frames(self) -> None:
        cmd, raw, sc, sup = self.command, self._raw, self.scaling, self.supervisor
        sc.encode_position(cmd.position, raw["target_position"])
        sc.encode_velocity(cmd.velocity, raw["target_velocity"])
        sc.encode_torque(cmd.torque, raw["target_torque"])
        modes = cmd.mode.tolist()
        states = self.state.cia402_state.tolist()
        tpos = raw["target_position"].tolist()
        tvel = raw["target_velocity"].tolist()
        ttrq = raw["target_torque"].tolist()
        actual = raw["position"].tolist()
        statuswords = raw["statusword"]
        now, enable = self._now, self.enable
        manager = self._manager
        if manager is not None and manager.switch_count != self._switches_seen:
            self._switches_seen = manager.switch_count  # a switch committed: arm who is ready
            self._armed = self.ready.tolist()
        armed = self._armed if manager is not None else None
        send_of = self._send_of
        homing = self._homing
        while self._homing_requests:
            request = self._homing_requests.popleft()
            homing[request.index] = self._homing_seen[request.index] = request
        for i, b in enumerate(self._bringup):
            if not b.mapped:
                continue
            send = send_of[i]
            job = homing[i]
            if job is not None:
                if self._home_step(i, b, job, states[i], now):
                    continue  # this cycle's homing frames are out
                homing[i] = None  # done: torque-off until the next switch (new reference)
                if armed is not None:
                    armed[i] = False
            if (b.phase != Phase.READY or sup.latched[i] is not None
                    or (armed is not None and not armed[i])):
                if armed is not None:  # off until the next switch: a drive that comes back
                    armed[i] = False   # (a recovery) never takes up a command it dropped
                for msg in self._start_frames(i, b):
                    send(msg)
                enable.reset(i)
                if self._pp[i]:
                    self._setpoints.reset(i)
                continue
            mode, st = modes[i], states[i]
            values: tuple[int, ...]
            if mode in _CYCLIC and not self._allowed_list[i] >> mode & 1:
                # limit_command stops this before it gets here; if a caller skipped it, the
                # drive's RPDO has no target for this mode: never send it, stop instead.
                sup.fault(i, f"commanded {JointMode(mode).name}, which it is not configured "
                             "for", now)
                mode = int(JointMode.TORQUE_OFF)
            if mode in _CYCLIC:
                cw = enable.controlword(i, st, now)
                carried = self._carrier[i][mode]
                if self._pp[i] and (st != OP_ENABLED or carried != _PP):
                    self._setpoints.reset(i)  # the next PP target is a new set-point
                if st != OP_ENABLED:  # enabling (or dropped out): hold the actual position
                    values = (cw, carried, actual[i], 0, 0)
                elif carried == _PP:
                    bits, target = self._setpoints.step(i, tpos[i], int(statuswords[i]))
                    values = (cw | bits, carried, target, tvel[i], ttrq[i])
                else:
                    if carried == _IP:
                        cw |= CW_ENABLE_INTERPOLATION
                    values = (cw, carried, tpos[i], tvel[i], ttrq[i])
            else:
                cw = _CW_QUICK_STOP if mode == JointMode.QUICK_STOP else 0
                values = (cw, self._default_mode[i], actual[i], 0, 0)
                enable.reset(i)
                if self._pp[i]:
                    self._setpoints.reset(i)
            self._send_rpdos(i, values, send)

    def _send_rpdos(self, i: int, values: tuple[int, ...],
                    send: Callable[[can.Message], None]) -> None:
        """Drive i's RPDOs packed from (controlword, mode, targets...) and sent."""
        constants = self._rpdo_constants[i]
        if constants:  # a fixed mapping's other objects: sent as the file gives them
            values += constants
        for msg, pack_into, where in self._rpdo_frames[i]:
            pack_into(msg.data, 0, *[values[k] for k in where])
            send(msg)

    def _home_step(self, i: int, b: DriveBringup, job: HomingJob, state: int,
                   now: float) -> bool:
        """One cycle of drive i's homing: True when its frames were sent, False when the job
        has ended (the caller then treats the drive as usual)."""
        if job.done():
            return False
        if b.phase != Phase.READY or self.supervisor.latched[i] is not None:
            job.fail("the drive faulted or left start-up state READY")
            return False
        cw = self.enable.controlword(i, state, now)
        homing_cw = job.step(state == OP_ENABLED, int(self._raw["statusword"][i]), now)
        if job.done():
            self.enable.reset(i)
            return False
        self._send_rpdos(i, (homing_cw if homing_cw is not None else cw, HOMING_MODE,
                             int(self._raw["position"][i]), 0, 0), self._send_of[i])
        return True

    def home(self, drive: str, timeout: float | None = None) -> Future[str]:
        """Home one drive (CiA 402 mode 6, its own method) over the following cycles, while
        the active controller keeps the others (homing.py). From any thread.

        Raises HomingFailed at once when the drive cannot be homed now (unknown, no homing
        mode in its 0x6502, no 0x6060 in its RPDO, not READY, faulted, already homing); the
        future then says how it ended ("NAME: homed", or HomingFailed)."""
        names = [d.name for d in self.drives_config]
        if drive not in names:
            raise HomingFailed(f"no drive named {drive!r} (drives: {', '.join(names)})")
        i = names.index(drive)
        plan, d = self.plans[i], self.drives_config[i]
        why = None
        if not plan.caps.supports(HOMING_MODE):
            why = (f"its 0x6502 (0x{plan.caps.supported_modes or 0:X}) has no homing mode; "
                   f"it lists {', '.join(plan.caps.mode_names)}")
        elif not self.layouts[i].maps("mode"):
            why = "its RPDO mapping carries no 0x6060, so the cycle cannot select homing"
        elif not self._bringup or self._bringup[i].phase != Phase.READY:
            why = "it is not READY (start-up or recovery not finished)"
        elif self.supervisor.latched[i] is not None:
            why = f"it is faulted ({self.supervisor.latched[i]}); recover it first"
        elif self._manager is not None and self._manager.state != ManagerState.OK:
            # the manager's own state: a switch that just committed is OK before the next
            # write tells this layer (should it e-stop meanwhile, write() fails the job)
            why = ("the manager is not OK: homing runs while a controller holds the other "
                   "joints (clear the e-stop and switch to one first)")
        with self._homing_lock:  # between callers only: the cycle never takes it
            seen = self._homing_seen[i]
            if why is None and seen is not None and not seen.done():
                why = "it is already homing"
            if why is not None:
                raise HomingFailed(f"{drive}: cannot home: {why}")
            future: Future[str] = Future()
            job = HomingJob(i, drive, timeout or d.homing_timeout, future)
            self._homing_seen[i] = job  # status shows this request, not the last result
            self._homing_requests.append(job)
        return future

    # --- the manager's limit_command -------------------------------------------------------------
    def limit_command(self, command: JointCommand) -> bool:
        """False (-> failure -> e-stop) for a mode a drive is not configured for, or NaN/inf.

        Finite targets are clipped in place to the configured joint limits.
        """
        mode = command.mode
        if int(mode.max()) > 15:
            return False
        np.left_shift(self._ones, mode, out=self._mode_bits)
        np.bitwise_and(self._mode_bits, self._allowed_modes, out=self._mode_bits)
        if np.count_nonzero(self._mode_bits) != len(self._mode_bits):
            return False
        if not (self._all_finite(command.position) and self._all_finite(command.velocity)
                and self._all_finite(command.torque)):
            return False
        self.scaling.clip_command(command.position, command.velocity, command.torque)
        return True

    def _all_finite(self, targets: np.ndarray) -> bool:
        """isfinite into a preallocated buffer, not a sum: inf + -inf would warn (and
        allocate)."""
        np.isfinite(targets, out=self._finite)
        return bool(self._finite.all())

    def neutral_command(self, command: JointCommand) -> None:
        """Targets for the fields a lower layer does not write itself: velocity and torque
        0; the position target at the actual position where the drive reports it (else
        the previous target when it is finite, else that joint quick-stops in firmware).
        The manager calls it on every fall to a lower layer, before the emergency
        controller writes, so the failed controller's targets (or its NaNs) are never sent
        in fields the emergency controller leaves alone. The emergency controller still
        owns its command: torque 0 in CST is no holding torque."""
        position = command.position
        np.copyto(position, self.state.position, where=self._position_fed)
        finite = self._finite
        np.isfinite(position, out=finite)
        if not finite.all():  # a fault path, rare: allocation is fine here
            stuck = ~finite
            position[stuck] = 0.0
            command.mode[stuck] = JointMode.QUICK_STOP
        command.velocity.fill(0.0)
        command.torque.fill(0.0)

    # --- recovery --------------------------------------------------------------------------------
    def recover(self, timeout: float = 5.0) -> Future[bool]:
        """Fault reset / restart every faulted or failed drive; Future[bool] says if all came back.

        Runs over the following cycles (never blocks the caller's thread or the cycle). On
        success the latched faults are cleared and, with a manager attached, its e-stop latch
        (``clear_emergency_stop``): switching is allowed again. The future is resolved on the
        cycle thread, so a done-callback must be trivial (or wait on the future elsewhere).
        """
        if self._recovery is not None and not self._recovery.done():
            return self._recovery
        future: Future[bool] = Future()
        self._recovery_timeout = timeout
        self._recovery_started = False
        self._recovery = future
        return future

    def _step_recovery(self, now: float) -> None:
        future = self._recovery
        if future is None or future.done():
            return
        sup = self.supervisor
        if not self._recovery_started:
            if sup.pending:  # a fault of this very cycle is delivered first, never erased
                return
            self._recovery_started = True
            self._recovery_deadline = now + self._recovery_timeout
            sup.bus_latched = None
            for port in self.ports:
                port.latched = None
            restarted: set[int] = set()
            for i, b in enumerate(self._bringup):
                if b.phase == Phase.READY and sup.latched[i] is None:
                    continue
                sup.disarm(i)
                sup.clear(i)
                self.state.error_code[i] = 0
                hb_ok = (self._hb_state[i] == cia301.NmtState.OPERATIONAL
                         and now - self._hb_time[i] < sup.heartbeat_timeout[i])
                if b.phase == Phase.READY and hb_ok:
                    b.reset_fault(now)
                elif b.phase != Phase.CONFIGURING:
                    b.restart(now, probe_at_once=True)
                    restarted.add(i)
            for i in restarted:  # a node configured again is NMT-reset: all its axes restart
                if self.plans[i].leads_node:
                    for k in self._node[i][1:]:
                        if k in restarted or self._bringup[k].phase == Phase.CONFIGURING:
                            continue
                        if self._bringup[k].phase == Phase.READY and sup.latched[k] is None:
                            # it may be under command: the manager hears it drop out (an
                            # e-stop, delivered this cycle), its configuration switched it
                            # off by SDO before the node's NMT pre-operational
                            sup.fault(k, "its node is configured again (recovery of drive "
                                         f"{self.drives_config[i].name!r})", now)
                        sup.disarm(k)
                        sup.clear(k)
                        self._bringup[k].restart(now, probe_at_once=True)
            return
        drives_ready = (all(b.phase == Phase.READY for b in self._bringup)
                        and not any(sup.latched) and sup.bus_latched is None)
        if drives_ready and min(p.clean_cycles for p in self.ports) >= sup.tpdo_timeout_cycles:
            if self._manager is not None:
                try:
                    self._manager.clear_emergency_stop()
                except Exception:  # the latch stays: this recovery did not finish
                    self.hook_errors += 1
                    future.set_result(False)
                    return
            future.set_result(True)
        elif now > self._recovery_deadline or (not drives_ready and all(
                b.phase in (Phase.READY, Phase.FAILED) for b in self._bringup)):
            future.set_result(False)

    # --- status --------------------------------------------------------------------------------
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
    def estop_cob_id(self) -> int:
        return self._estop_cob_id

    def estop_conflict(self, cob_id: int) -> str | None:
        """Why ``cob_id`` cannot be the e-stop frame's on these buses, or None: a reserved
        id, or one a drive or the manager's own node uses (an e-stop taken for a drive's
        frame, or a drive's frame taken for an e-stop, would both be wrong)."""
        why = estop_conflict(cob_id, self.drives_config, self.manager_node_id)
        if why is not None:
            return why
        for plan in self.plans:
            for pdo in (*plan.layout.rpdos, *plan.layout.tpdos):
                if pdo.cob_id == cob_id:  # an absolute COB-ID from the drive's EDS/DCF
                    return f"a PDO of drive {plan.drive.name!r}"
        return None

    def set_estop_cob_id(self, cob_id: int) -> None:
        """The e-stop frame's COB-ID on every bus (0 = off), from any thread: the manager
        node calls it when 0x2130 is written. ValueError for an id that is not free."""
        if not _whole_cob_id(cob_id):
            raise ValueError(f"estop_cob_id must be 0 (off) or an 11-bit COB-ID, got {cob_id!r}")
        why = self.estop_conflict(cob_id) if cob_id else None
        if why is not None:
            raise ValueError(f"estop_cob_id 0x{cob_id:03X} is {why}")
        self._estop_cob_id = cob_id
        for port in self.ports:
            port.set_estop_cob_id(cob_id)

    @property
    def frames_per_cycle(self) -> int:
        """RPDOs + TPDOs of every drive + 1 SYNC per bus (the manager heartbeat is not per
        cycle)."""
        return sum(lay.frames_per_cycle for lay in self.layouts) + len(self.ports)

    @property
    def ready(self) -> np.ndarray:
        """Per drive: brought up, no latched fault (torque off until a controller enables it)."""
        return np.array([b.phase == Phase.READY and self.supervisor.latched[i] is None
                         for i, b in enumerate(self._bringup)], dtype=bool)

    @property
    def all_ready(self) -> bool:
        return bool(self._bringup) and bool(self.ready.all())

    @property
    def starting(self) -> bool:
        """Some drive is still in bring-up (neither READY nor FAILED)."""
        return any(b.phase not in (Phase.READY, Phase.FAILED) for b in self._bringup)

    @property
    def enabled(self) -> np.ndarray:
        enabled: np.ndarray = self.ready & (self.state.cia402_state
                                            == State402.OPERATION_ENABLED)
        return enabled

    @property
    def all_enabled(self) -> bool:
        return bool(self._bringup) and bool(self.enabled.all())

    def not_ready(self, required: Sequence[int] | None = None) -> str | None:
        """Why the drives cannot be commanded now, or None: the manager's switch guard (a
        switch into a controller needs its drives brought up and free of latched faults,
        so clearing an e-stop latch never re-arms a faulted drive). ``required``: indices
        of the drives that must be ready (default: every drive)."""
        if not self._bringup:
            return "the drives are not started"
        if self._recovery is not None and not self._recovery.done():
            return "a recovery is in progress"
        sup = self.supervisor
        if sup.bus_latched is not None:
            return f"bus fault: {sup.bus_latched.cause} (recover first)"
        waiting = []
        for i in range(len(self._bringup)) if required is None else required:
            b, latched, name = self._bringup[i], sup.latched[i], self.drives_config[i].name
            if latched is not None:
                waiting.append(f"{name} (fault: {latched.cause}; recover first)")
            elif b.phase != Phase.READY:
                waiting.append(f"{name} ({b.phase.name}" + (f": {b.failure})" if b.failure
                                                             else ")"))
        return "drives not ready: " + ", ".join(waiting) if waiting else None

    def drive_status(self) -> list[DriveStatus]:
        """A snapshot (from any thread: it only reads), one entry per configured drive."""
        out = []
        enabled = self.enabled if self._bringup else np.zeros(len(self.drives_config), bool)
        now = time.monotonic()
        for i, d in enumerate(self.drives_config):
            b = self._bringup[i] if self._bringup else None
            latched = self.supervisor.latched[i]
            fault = str(latched.cause) if latched is not None else (b.failure if b else None)
            nmt = self._hb_state[i]
            seen = float(self._hb_time[i])
            out.append(DriveStatus(
                d.name, d.node_id, b.phase.name if b else "NOT_STARTED",
                State402(int(self.state.cia402_state[i])).name, bool(enabled[i]), fault,
                cia301.NmtState(nmt).name if nmt in cia301.NmtState._value2member_map_
                else "UNKNOWN",
                round(now - seen, 3) if math.isfinite(seen) else None,
                job.describe() if (job := self._homing_seen[i]) is not None else "",
                *(_reported(source[i], kind in (d.feedback or ()))
                  for kind, source in (("position", self.state.position),
                                       ("velocity", self.state.velocity),
                                       ("torque", self.state.torque)))))
        return out

    def status_report(self) -> dict[str, Any]:
        """What the manager node serves as 0x2140 (JSON) and ``rocoma-can status`` prints:
        whether start-up has finished, what a recovery is doing, and every drive."""
        future = self._recovery
        if future is None:
            recovery = "none"
        elif not future.done():
            waiting = [f"{d.name} ({d.phase})" for d in self.drive_status()
                       if d.phase != "READY" or d.fault]
            recovery = "running" + (f": waiting for {', '.join(waiting)}" if waiting else "")
        else:
            recovery = "succeeded" if future.result() else "failed"
        return {"startup_finished": bool(self._bringup) and not self.starting,
                "recovery": recovery, "bus_fault": self.bus_fault,
                "buses": [{"name": p.name, "channel": p.channel, "fault": p.latched,
                           "tx_errors": p.tx_errors, "error_frames": p.error_frames}
                          for p in self.ports],
                "drives": [dataclasses.asdict(d) for d in self.drive_status()]}
