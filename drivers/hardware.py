"""The CAN hardware layer: N CiA 402 drives as one JointState / JointCommand pair.

One cycle, on the one thread that owns the loop (``run_cycle`` does exactly this)::

    hw.read(now)       drain received frames -> JointState; bring-up steps; supervision
    manager.update()   the active layer writes JointCommand
    hw.write(state)    RPDOs (or torque-off frames) for every drive, SYNC, manager heartbeat

The safety path, top to bottom (each step names where it lives):

1. A drive goes wrong. Supervision (supervision.py) turns every symptom into a FaultEvent:
   EMCY, statusword fault bit, heartbeat deadline or non-operational heartbeat, TPDOs missing
   for k cycles, a drive dropping out of operation enabled or not enabling in time
   (``_command_frames`` below), a bus-off error frame (``_on_error_frames``), or the bus
   refusing frames in ``tpdo_timeout_cycles`` cycles in a row (``_end_of_write``). Frames
   arrive on the bus reader thread (bus.py), which only appends them to a deque; ``read``
   drains it on the cycle thread, so no lock is shared with a slow thread.
2. The faulted drive gets torque-off frames from the same cycle on (``_command_frames``:
   a latched drive is never sent anything but controlword 0x0000), until recovery, and
   controlword 0x0000 once by SDO from a thread of its own (``_deliver``, switch_off.py): a
   drive that no longer applies RPDOs (pre-operational, ignoring SYNC) still switches off.
3. ``read`` hands the event to the manager before update(): ``manager.emergency_stop(cause)``
   (``_deliver``; ``rocoma_can.runtime.system.manager_for`` wires it). In update() the
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
   (``ControllerManager._run_watchdog``) calls ``send_torque_off`` every cycle until it
   returns: the pre-encoded frames and SYNC, no heartbeat. The hung advance then counts as a
   failure and the manager goes straight to FAILPROOF (the drives are off already).
7. If the loop itself dies or hangs, nothing is sent at all, including the manager
   heartbeat (produced by ``write``, never by a kernel BCM task that would outlive the
   process; the manager's CANopen node cannot start one either: runtime/node.py). Each
   drive's heartbeat consumer (0x1016, set at start-up by bringup.configure) times out and
   its abort connection option (0x6007 = 2, disable voltage) switches the power stage off.
   A consumer watches only after the first heartbeat it receives, so ``_step_bringup`` has
   one sent in the cycle a drive's configuration completes, before it can become READY.

Start-up (bringup.py) never enables a drive; it ends in READY (torque off). Drives are enabled
step by step from the cyclic controlword (``_command_frames``, enable.py) only while the
manager is OK or EMERGENCY and the active layer commands a cyclic mode for them. Recovery
(``recover``) resets or restarts latched and failed drives over the following cycles.

This is everything software over CAN can do, and it is not a certified safe torque off: a
bus-off, a babbling node or firmware that ignores the controlword defeats it. Hard-wired STO
inputs or CANopen Safety (SRDO) are needed for that (README, safety model). The README
points here for these steps instead of keeping a second copy.
"""
from __future__ import annotations

import collections
import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

import can
import numpy as np

from ..events import ManagerState
from . import cia301, cia402
from .bringup import DriveBringup, Phase
from .bus import CanopenBus, open_bus
from .cia402 import State402
from .config import BusConfig, DriveConfig, Supervision, check_drives
from .enable import OP_ENABLED, EnableSequence
from .frame_io import FrameWriter, clock_offset, to_monotonic
from .joints import JointCommand, JointMode, JointState
from .pdo_layout import RPDO_FIELDS, DriveLayout, drive_object_dictionary, layout_for
from .scaling import Scaling
from .supervision import FaultEvent, Supervisor
from .switch_off import SdoSwitchOff

_CW_FAULT_RESET = int(cia402.Controlword.FAULT_RESET)
_CW_QUICK_STOP = int(cia402.Controlword.QUICK_STOP)
_CYCLIC = (int(JointMode.CSP), int(JointMode.CSV), int(JointMode.CST))


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


#: Linux CAN error class of a bus-off error frame (linux/can/error.h CAN_ERR_BUSOFF)
CAN_ERR_BUSOFF = 0x40


class _Receiver(can.Listener):
    """Runs on the bus reader thread: filter by COB-ID, append. Nothing else.

    Frames keep their arrival stamp (kernel or python-can, wall clock); ``read`` converts it
    to the monotonic clock once per cycle, so a reader that lags does not make frames late.
    """

    def __init__(self, cob_ids: set[int], sink: collections.deque[can.Message],
                 errors: collections.deque[can.Message]) -> None:
        self._ids = frozenset(cob_ids)
        self._sink = sink
        self._errors = errors

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self._errors.append(msg)
        elif msg.arbitration_id in self._ids and not (msg.is_extended_id or msg.is_remote_frame):
            self._sink.append(msg)  # only 11-bit data frames are CANopen: 0x181 (29 bit) is not

    def on_error(self, exc: Exception) -> None:  # counted by the reader; nothing to do here
        pass


class Manager(Protocol):
    """What the hardware needs of the manager it is attached to (rocoma_can's
    ControllerManager): nothing in drivers/ builds or imports one."""
    switch_count: int

    def update(self) -> ManagerState: ...
    def emergency_stop(self, cause: str = ...) -> None: ...
    def clear_emergency_stop(self) -> bool: ...


def _frame(cob_id: int, size: int) -> can.Message:
    return can.Message(arbitration_id=cob_id, data=bytearray(size), is_extended_id=False)


class CanopenHardware:
    """CiA 402 drives on one CAN bus, cycled by the control loop."""

    def __init__(self, bus: can.BusABC | BusConfig, drives: Sequence[DriveConfig],
                 manager_node_id: int, dt: float, *,
                 manager_heartbeat_ms: int = 100, supervision: Supervision | None = None,
                 config_workers: int = 4,
                 on_fault: Callable[[FaultEvent], None] | None = None) -> None:
        drives = list(drives)
        check_drives(drives, manager_node_id)
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
        self._bus_arg = bus
        n = len(drives)
        names = [d.name for d in drives]
        self.state = JointState.zeros(names)
        self.command = JointCommand.zeros(names)
        self.layouts: list[DriveLayout] = [layout_for(d) for d in drives]
        self.scaling = Scaling(drives)
        self.supervisor = Supervisor(drives, supervision.tpdo_timeout_cycles,
                                     supervision.heartbeat_timeout_factor)
        self._ods = [drive_object_dictionary(d, layout) for d, layout in zip(drives, self.layouts)]

        # --- raw bus values, one slot per drive (the codecs read and write these) ---------
        self._raw = {name: np.zeros(n, dtype=np.int64) for name in
                     ("statusword", "position", "velocity", "torque",
                      "target_position", "target_velocity", "target_torque")}
        self._allowed_modes = np.array(
            [(1 << JointMode.TORQUE_OFF) | (1 << JointMode.QUICK_STOP)
             | sum(1 << int(m) for m in d.modes) for d in drives], dtype=np.int64)
        self._allowed_list = self._allowed_modes.tolist()
        self._mode_bits = np.zeros(n, dtype=np.int64)
        self._ones = np.ones(n, dtype=np.int64)
        self._finite = np.zeros(n, dtype=bool)
        self._position_fed = np.array(["position" in d.feedback for d in drives], dtype=bool)
        self._default_mode = [int(d.modes[0]) for d in drives]
        self._got = np.zeros(n, dtype=np.int64)             # TPDO bits seen this cycle
        self._expected = np.array([(1 << len(lay.tpdos)) - 1 for lay in self.layouts],
                                  dtype=np.int64)
        self._complete = np.zeros(n, dtype=bool)
        self.enable = EnableSequence(n, supervision.timeouts.enable, self.supervisor.fault)
        # The drives the active controller may command: those ready when its switch was
        # committed. A drive ready only later (recovered, late start) stays torque-off
        # until the next switch: that controller never saw it (its pose, its limits).
        self._armed = [False] * n
        self._switches_seen = -1
        self._hb_state = [-1] * n
        self._hb_time = np.full(n, -math.inf)

        # --- receive tables: COB-ID -> what to do with the frame ---------------------------
        self._tpdo_of: dict[int, tuple[int, int, int, Callable[..., tuple[int, ...]],
                                       tuple[np.ndarray, ...]]] = {}
        for i, layout in enumerate(self.layouts):
            for pdo in layout.tpdos:
                self._tpdo_of[pdo.cob_id] = (i, 1 << (pdo.number - 1), pdo.size,
                                             pdo.codec.unpack_from,
                                             tuple(self._raw[name] for name in pdo.names))
        self._index_of_node = {d.node_id: i for i, d in enumerate(drives)}
        self._heartbeat_of = {cia301.HEARTBEAT + d.node_id: i for i, d in enumerate(drives)}
        self._emcy_of = {cia301.EMCY + d.node_id: i for i, d in enumerate(drives)}
        self._rx: collections.deque[can.Message] = collections.deque()
        self._rx_errors: collections.deque[can.Message] = collections.deque(maxlen=1024)

        # --- transmit frames, allocated once -------------------------------------------------
        # Per drive and RPDO: (frame, codec.pack_into, positions of its entries in RPDO_FIELDS)
        self._rpdo_frames = [[(_frame(p.cob_id, p.size), p.codec.pack_into,
                               p.positions_in(RPDO_FIELDS)) for p in lay.rpdos]
                             for lay in self.layouts]
        self._torque_off_frames = [self._preencode(i, 0) for i in range(n)]
        self._fault_reset_frames = [self._preencode(i, _CW_FAULT_RESET) for i in range(n)]
        self._probe_frames = [self._preencode(i, int(cia402.Controlword.SHUTDOWN))
                              for i in range(n)]
        self._sync = _frame(cia301.SYNC, 0)
        self._heartbeat = can.Message(arbitration_id=cia301.HEARTBEAT + manager_node_id,
                                      data=bytearray([cia301.NmtState.OPERATIONAL]),
                                      is_extended_id=False)
        self._next_heartbeat = -math.inf

        self._canopen: CanopenBus | None = None
        self._writer: FrameWriter | None = None
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
        self.tx_errors = 0     # frames the bus refused (counted, never raised)
        self.last_tx_error: Exception | None = None
        self._tx_refused = False     # a frame was refused since the last write
        self._tx_refused_cycles = 0  # writes in a row with a refused frame
        self._tx_clean_cycles = 0    # writes in a row without one (a recovery needs a run)
        self.rx_bad = 0        # TPDOs with a length other than their mapping's (never decoded)
        self.hook_errors = 0   # on_fault calls that raised (counted, never raised)
        self.error_frames = 0  # CAN error frames received (bus-off ones are a fault)
        self.cycles = 0

    def _preencode(self, i: int, controlword: int) -> list[can.Message]:
        """Torque-off frames for drive i: controlword, the default mode, every target 0."""
        values = (controlword, self._default_mode[i], 0, 0, 0)
        frames = []
        for pdo in self.layouts[i].rpdos:
            msg = _frame(pdo.cob_id, pdo.size)
            pdo.codec.pack_into(msg.data, 0, *(values[k] for k in pdo.positions_in(RPDO_FIELDS)))
            frames.append(msg)
        return frames

    # --- life cycle ---------------------------------------------------------------------------
    def start(self, now: float | None = None) -> None:
        """Open the bus (unless lent), attach the receiver, begin every drive's bring-up."""
        if self._canopen is not None:
            raise RuntimeError("CanopenHardware.start() called twice")
        now = time.monotonic() if now is None else now
        if isinstance(self._bus_arg, BusConfig):
            cfg = self._bus_arg
            cb = CanopenBus(open_bus(cfg.interface, cfg.channel, cfg.bitrate), own_bus=True)
        else:
            cb = CanopenBus(self._bus_arg)
        self._canopen = cb
        self._writer = cb.writer
        cob_ids = set(self._tpdo_of) | set(self._heartbeat_of) | set(self._emcy_of)
        cb.add_listener(_Receiver(cob_ids, self._rx, self._rx_errors))
        self._switch_off = SdoSwitchOff()
        self._switch_off.start()
        self._executor = ThreadPoolExecutor(
            max_workers=min(self.config_workers, len(self.drives_config)),
            thread_name_prefix="canopen-config")
        for d, layout, od in zip(self.drives_config, self.layouts, self._ods):
            node = cb.network.add_node(d.node_id, od)
            # No retransmission by default (CiA 301 clients abort on timeout): a late answer
            # to the first copy would be taken as the answer to the next request. configure()
            # repeats a whole failed attempt instead, after stale answers have drained.
            node.sdo.RESPONSE_TIMEOUT = self.supervision.sdo_timeout
            # canopen counts tries (0 = forever)
            node.sdo.MAX_RETRIES = self.supervision.sdo_retries + 1
            b = DriveBringup(d, layout, node, self.manager_node_id, self.consumer_ms,
                             self.timeouts)
            b.restart(now)
            self._bringup.append(b)
        self._now = now

    def close(self) -> None:
        """Join the configuration workers and the bus reader; shut the bus if opened here."""
        for b in self._bringup:
            b.cancel()
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        self._switch_off.close()
        if self._canopen is not None:
            self._canopen.close()
            self._canopen = None
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
        """read, manager.update, write: one whole cycle (needs ``attach``, which
        ``rocoma_can.runtime.system.manager_for`` does)."""
        if self._manager is None:
            raise RuntimeError("run_cycle needs a manager: attach() one first")
        self.read(time.monotonic() if now is None else now)
        state = self._manager.update()
        self.write(state)
        return state

    # --- the cycle ------------------------------------------------------------------------------
    def read(self, now: float) -> None:
        """Drain frames into JointState, step bring-up and recovery, raise fault events."""
        self._now = now
        sup = self.supervisor
        got = self._got
        got.fill(0)
        rx = self._rx
        tpdo_of, heartbeat_of, emcy_of = self._tpdo_of, self._heartbeat_of, self._emcy_of
        stamp = self.state.stamp
        offset = clock_offset()
        while rx:
            msg = rx.popleft()
            t = to_monotonic(offset, msg.timestamp, now)
            cob = msg.arbitration_id
            entry = tpdo_of.get(cob)
            if entry is not None:
                i, bit, size, unpack, targets = entry
                if msg.dlc != size:  # not what we mapped: never decoded, a fault once supervised
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
            j = emcy_of.get(cob)
            if j is not None and msg.dlc >= 2:
                code = msg.data[0] | (msg.data[1] << 8)
                self.state.error_code[j] = code
                if code == cia301.EMCY_STO:
                    self._bringup[j].sto_seen = True
                sup.on_emcy(j, code, t)
        if self._rx_errors:
            self._on_error_frames(offset, now)
        np.equal(got, self._expected, out=self._complete)
        self._decode(now)
        self._step_bringup(now)
        sup.tick(now, self._complete, self.state.cia402_state, self.state.error_code)
        self._step_recovery(now)
        self._deliver(sup.take_pending())
        self.cycles += 1

    def _on_error_frames(self, offset: float, now: float) -> None:
        errors = self._rx_errors
        while errors:
            msg = errors.popleft()
            self.error_frames += 1
            if msg.arbitration_id & CAN_ERR_BUSOFF:
                self.supervisor.bus_fault(f"CAN bus-off (error frame class "
                                          f"0x{msg.arbitration_id:X})",
                                          to_monotonic(offset, msg.timestamp, now))

    def _on_heartbeat(self, i: int, nmt_state: int, t: float) -> None:
        self._hb_state[i] = nmt_state
        self._hb_time[i] = t
        self._bringup[i].alive = True
        self.supervisor.on_heartbeat(i, nmt_state, t)

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
            elif phase == Phase.CONFIGURING and b.phase == Phase.STARTING:
                # The drive's heartbeat consumer was just (re)configured, and it only starts
                # watching with the first heartbeat it receives: send one in this cycle, so
                # the drive is protected before it can become READY (a TPDO round trip later).
                self._next_heartbeat = -math.inf

    def _still_latched(self, i: int, event: FaultEvent) -> Callable[[], bool]:
        """For the SDO switch-off: whether drive i is still latched by ``event``."""
        latched = self.supervisor.latched
        return lambda: latched[i] is event

    def _deliver(self, events: list[FaultEvent]) -> None:
        sup = self.supervisor
        for event in events:
            if self._manager is not None:
                self._manager.emergency_stop(cause=str(event))  # a deque append: cannot fail
            i = self._index_of_node.get(event.node_id)
            if (i is not None and i < len(self._bringup) and self._bringup[i].mapped
                    and sup.latched[i] is event):  # a queue append: cannot block
                self._switch_off.request(self._bringup[i], self._still_latched(i, event))
            if self.on_fault is not None:
                try:
                    self.on_fault(event)
                except Exception:  # a reporting hook must not take the cycle down
                    self.hook_errors += 1

    def write(self, manager_state: ManagerState) -> None:
        """Command frames (or torque-off frames in FAILPROOF), then SYNC, then heartbeat."""
        if manager_state == ManagerState.FAILPROOF:
            self._torque_off()
        else:
            try:
                self._command_frames()
            except Exception:  # a bug here must still end in torque-off
                self.tx_errors += 1
                self._torque_off()
        self._send(self._sync)
        if self._now >= self._next_heartbeat:
            self._send(self._heartbeat)
            self._next_heartbeat = self._now + self.manager_heartbeat_period
        self._end_of_write()

    def _send(self, msg: can.Message) -> None:
        try:
            self._writer.send_message(msg)  # type: ignore[union-attr]
        except Exception as exc:  # a full queue, a failed interface, or not started/closed
            self.tx_errors += 1
            self.last_tx_error = exc
            self._tx_refused = True

    def _end_of_write(self) -> None:
        """A bus that refuses frames cycle after cycle (transmit queue full, interface down)
        delivers no command and no heartbeat: after as many cycles as missing TPDOs are
        tolerated it is a bus fault, an e-stop like bus-off. One refused frame is not (a
        transmit queue can be full for a moment); the frames are tried again every cycle. A
        recovery succeeds only after as many cycles in a row without a refused frame."""
        sup = self.supervisor
        if not self._tx_refused:
            self._tx_refused_cycles = 0
            if self._tx_clean_cycles < sup.tpdo_timeout_cycles:
                self._tx_clean_cycles += 1
            return
        self._tx_refused = False
        self._tx_clean_cycles = 0
        self._tx_refused_cycles += 1
        if self._tx_refused_cycles >= sup.tpdo_timeout_cycles and sup.bus_latched is None:
            sup.bus_fault(f"the bus refused frames in {self._tx_refused_cycles} cycles in a "
                          f"row (last: {self.last_tx_error})", self._now)

    def _torque_off(self) -> None:
        """FAILPROOF: pre-encoded disable-voltage frames to every configured drive."""
        for i, b in enumerate(self._bringup):
            if b.mapped:
                for msg in self._start_frames(i, b):
                    self._send(msg)
            self.enable.reset(i)

    def send_torque_off(self) -> None:
        """Torque-off frames to every mapped drive, then SYNC, from any thread.

        The manager's hang watchdog calls this while update() is stuck in a controller (the
        cycle sends nothing then). It only sends pre-encoded frames and touches no cycle
        state; it sends no heartbeat, so the drives' own heartbeat consumers still time out
        if the loop never comes back.
        """
        for i, b in enumerate(self._bringup):
            if b.mapped:
                for msg in self._torque_off_frames[i]:
                    self._send(msg)
        self._send(self._sync)

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
        now, enable = self._now, self.enable
        manager = self._manager
        if manager is not None and manager.switch_count != self._switches_seen:
            self._switches_seen = manager.switch_count  # a switch committed: arm who is ready
            self._armed = self.ready.tolist()
        armed = self._armed if manager is not None else None
        for i, b in enumerate(self._bringup):
            if not b.mapped:
                continue
            if (b.phase != Phase.READY or sup.latched[i] is not None
                    or (armed is not None and not armed[i])):
                for msg in self._start_frames(i, b):
                    self._send(msg)
                enable.reset(i)
                continue
            mode, st = modes[i], states[i]
            if mode in _CYCLIC and not self._allowed_list[i] >> mode & 1:
                # limit_command stops this before it gets here; if a caller skipped it, the
                # drive's RPDO has no target for this mode: never send it, stop instead.
                sup.fault(i, f"commanded {JointMode(mode).name}, which it is not configured "
                             "for", now)
                mode = int(JointMode.TORQUE_OFF)
            if mode in _CYCLIC:
                cw = enable.controlword(i, st, now)
                if st == OP_ENABLED:
                    values = (cw, mode, tpos[i], tvel[i], ttrq[i])
                else:  # enabling (or dropped out): hold the actual position, no jump
                    values = (cw, mode, actual[i], 0, 0)
            else:
                cw = _CW_QUICK_STOP if mode == JointMode.QUICK_STOP else 0
                values = (cw, self._default_mode[i], actual[i], 0, 0)
                enable.reset(i)
            for msg, pack_into, where in self._rpdo_frames[i]:
                pack_into(msg.data, 0, *[values[k] for k in where])
                self._send(msg)

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
            self._recovery_started = True
            self._recovery_deadline = now + self._recovery_timeout
            sup.bus_latched = None
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
            return
        drives_ready = (all(b.phase == Phase.READY for b in self._bringup)
                        and not any(sup.latched) and sup.bus_latched is None)
        if drives_ready and self._tx_clean_cycles >= sup.tpdo_timeout_cycles:
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
        """The latched bus-level fault (bus-off), None when there is none."""
        event = self.supervisor.bus_latched
        return None if event is None else event.cause

    @property
    def frames_per_cycle(self) -> int:
        """RPDOs + TPDOs of every drive + 1 SYNC (the manager heartbeat is not per cycle)."""
        return sum(lay.frames_per_cycle for lay in self.layouts) + 1

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
                round(now - seen, 3) if math.isfinite(seen) else None))
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
                "drives": [dataclasses.asdict(d) for d in self.drive_status()]}
