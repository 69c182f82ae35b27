"""A simulated CAN bus segment: many simulated CiA 402 drives on ONE python-can bus.

One bus (one socket on SocketCAN), one receive thread that dispatches frames by COB-ID, and
one timer thread for heartbeats, consumer deadlines, late TPDOs and babbling. Both run the
drives with the segment lock held, so a drive never sees two events at once. Exceptions in
either thread are caught and kept in ``segment.errors`` (a callback that raised would
otherwise end a reader thread silently); ``segment.check()`` re-raises the first one. A bus
that cannot be read (its interface went down or away) is the bus's fault, not the
simulation's: counted in ``bus_errors`` and read again every ``RX_IDLE``.

Time: the joints are integrated on each SYNC over the time since the previous SYNC
(monotonic, clipped to ``max_dt``), or over a fixed ``sync_period`` when one is given, which
makes runs deterministic. Without a fixed period the drives keep running between SYNCs too
(``free_run_period``), so a ramp or a coasting joint continues after the master has died;
but only over a silence the reader has seen (``received_until``): a reader that lags has
SYNCs queued, and a long step on the timer (up to ``max_dt``, under the lock) would only
make it lag more.

Arrival times: a real drive's CAN controller takes each frame as it arrives; this segment is
one Python thread that may lag behind its socket (a loaded machine, a slow virtual machine).
So SYNC steps and heartbeats use the time each frame arrived (the kernel's or python-can's
stamp), and a heartbeat consumer declares a loss only once every frame that arrived before
its deadline has been handled (``received_until``). Without that, heartbeats sent well in
time but still queued would read as lost, and the drives would switch off for nothing.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import can
import numpy as np

from ..commission.lss import LSS_REQUEST, UNCONFIGURED
from ..link.bus import enlarge_bus_buffer
from ..link.frame_io import FrameReader, FrameWriter, clock_offset, to_monotonic
from ..protocol import cia301 as c301
from .dynamics import JointDynamics
from .lss import LssSlave, check_addresses
from .nodes_on_bus import NodesOnBus
from .objects import (
    fallback_values,
    load_object_dictionaries,
    log_file_notes,
    own_identity,
)
from .port import Route
from .segment_options import SegmentOptions
from .timers import RX_IDLE, Timers

log = logging.getLogger(__name__)

#: Frames handled under one lock hold: bounded so timers still run during a flood.
RX_BATCH = 64
#: Longest a segment's SYNC waits for the other segments' of its group before its joints
#: step alone (group.py). One cycle's SYNCs on every bus come within one write of the
#: master (in process, a fraction of this); the wait delays the answers to the first ones by
#: as much at most. A timer event of a segment whose step waits comes after the step.
JOIN_WAIT = 0.0002


def _default_eds() -> str:
    from rocoma_can import eds  # the EDS shipped with the package
    return str(eds.path(eds.CIA402_DRIVE))


class SimulatedSegment:
    """Simulated CiA 402 drives sharing one python-can bus.

    How they are made and run: ``options`` (segment_options.py). Each axis of a node is a
    joint of ``dynamics``, numbered in order of node id, then axis (node 1 axis 1, node 1
    axis 2, node 2 axis 1, ...); unconfigured nodes' joints come after the configured
    nodes'. Every node with a whole identity is an LSS slave (``lss_slaves``); ``drives``
    holds the nodes on the bus now, by node id. ``own_bus``: the segment shuts the bus
    down when it stops.
    """

    def __init__(self, bus: can.BusABC, node_ids: Iterable[int],
                 options: SegmentOptions | None = None, *, own_bus: bool = False) -> None:
        ids = sorted(set(int(n) for n in node_ids))
        options = options or SegmentOptions()
        options.check(ids)
        self.options = options
        axis_count = {n: options.axes.get(n, 1) for n in ids}
        self.bus = enlarge_bus_buffer(bus)  # the one receive thread may lag behind its socket
        self.node_ids = tuple(ids)
        self.sync_period = options.sync_period
        self.max_dt = options.max_dt
        self.free_run_period = options.free_run_period if options.sync_period is None else None
        self.lock = threading.RLock()
        self.rng = np.random.default_rng(options.seed)
        self.errors: list[BaseException] = []  # the simulation's own failures (check())
        self.send_errors = 0
        # reads of the bus that failed (its interface went down or away): the bus's fault,
        # not the simulation's; read again every RX_IDLE
        self.bus_errors = 0
        self.bus_error: BaseException | None = None  # the latest
        self._bus_down = False  # failing now (for the one "reads again" log line)
        self.sync_count = 0  # SYNC and NMT frames handled: tests wait on these
        self.nmt_count = 0
        self._own_bus = own_bus
        joints = [(n, a) for n in ids for a in range(1, axis_count[n] + 1)]
        self.dynamics = JointDynamics(options.joint_params(joints))
        options.check_scaling()
        self._eds = eds = str(options.eds_path) if options.eds_path else _default_eds()
        # what the drives assume where the file has no object (scaling: these numbers)
        dictionaries = load_object_dictionaries(eds, ids or [1])
        template = next(iter(dictionaries.values()))
        self._fallbacks = fallback_values(options.increments_per_rev, options.rated_torque_nm,
                                          template)
        self._overrides = dict(options.overrides)
        # an FD bus: the drives answer in FD frames and map PDOs of up to 64 bytes
        self._writer = FrameWriter(bus, fd=options.fd)
        self._nodes = nodes = NodesOnBus(self, eds, self._fallbacks, self._overrides)
        self.drives = nodes.drives
        self.lss_slaves = nodes.lss_slaves
        for n in ids:
            identity = own_identity(template, n, self._overrides, options.identities.get(n))
            nodes.put_on_bus(n, joints.index((n, 1)), axis_count[n], identity, dictionaries[n])
            if len(identity.objects()) == 4:  # an LSS address needs all four
                self.lss_slaves.append(LssSlave(identity, n, joints.index((n, 1)),
                                                axis_count[n], self.send, nodes.move))
        for k, given in enumerate(options.unconfigured):
            self.lss_slaves.append(LssSlave(
                own_identity(template, UNCONFIGURED, self._overrides, given), UNCONFIGURED,
                len(joints) + k, 1, self.send, nodes.move))
        check_addresses(self.lss_slaves)
        if self.drives:
            log_file_notes(log, eds, next(iter(self.drives.values())).objects)
        self._last_step: float | None = None
        # A SegmentGroup that steps its segments' joints together (group.py) leaves a SYNC's
        # dynamics step to itself: ``deferred_dt`` is the step this segment's drives are
        # prepared for, until the group steps every such segment at once (``finish_joined``)
        # or a frame to this segment needs it taken now (``finish_deferred``).
        self._defer_steps = False
        self.deferred_dt: float | None = None
        self._deferred_at = -math.inf  # when (monotonic) the step was deferred
        # Every frame that arrived (monotonic) before this has been handled: see the docstring.
        self.received_until = -math.inf
        self._backlog: list[can.Message] = []  # see pump
        self._timers = Timers(self._run_timer)
        self._stopped = threading.Event()
        self._rx_thread = threading.Thread(target=self._receive_loop,
                                           name="sim-segment-rx", daemon=True)
        self._started = False

    @classmethod
    def open(cls, channel: str, interface: str = "virtual", node_ids: Iterable[int] = (1,),
             **options: Any) -> SimulatedSegment:
        """A segment on its own new bus (shut down with the segment); ``options``: the
        fields of SegmentOptions."""
        extra: dict[str, Any] = ({"fd": True} if options.get("fd")
                                 and interface in ("socketcan", "inproc") else {})
        bus = can.Bus(interface=interface, channel=channel, receive_own_messages=False,
                      ignore_config=True, **extra)
        try:
            return cls(bus, node_ids, SegmentOptions.of(**options), own_bus=True)
        except BaseException:
            bus.shutdown()
            raise

    # ------------------------------------------------------------------ life cycle
    def start(self, receive: bool = True) -> SimulatedSegment:
        """Power on every drive (boot-up frames), then start receiving and the timers.

        ``receive=False``: no receive thread of its own; a SegmentGroup (group.py) reads
        this segment's bus together with others' on one thread and calls ``pump``."""
        if self._started:
            raise RuntimeError("simulated segment already started")
        self._started = True
        with self.lock:
            for drive in self.drives.values():
                drive.power_on()  # an unconfigured node: silent until it has a node id
            self._last_step = self.clock()
        if receive:
            self._rx_thread.start()
        self._timers.start()
        if self.free_run_period:
            self.schedule(self.clock() + self.free_run_period, self._free_run)
        return self

    def stop(self) -> None:
        self._stopped.set()
        self._timers.stop()
        if self._rx_thread.is_alive():
            self._rx_thread.join(2.0)
        if self._own_bus:
            self.bus.shutdown()

    def __enter__(self) -> SimulatedSegment:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def check(self) -> None:
        """Re-raise the first exception a segment thread caught, if any."""
        if self.errors:
            raise RuntimeError(f"simulated segment failed: {self.errors[0]!r}") from self.errors[0]

    # ------------------------------------------------------------------ services for drives
    @staticmethod
    def clock() -> float:
        return time.monotonic()

    def schedule(self, when: float, fn: Callable[..., Any], *args: Any) -> None:
        self._timers.call_at(when, fn, args)

    @property
    def fd(self) -> bool:
        return self._writer.fd

    def send(self, cob_id: int, data: bytes) -> None:
        try:
            self._writer.send(cob_id, data)
        except can.CanError as exc:  # ENOBUFS, bus closed: a real drive just loses it
            self._send_failed(cob_id, exc)

    def send_frame(self, msg: can.Message) -> None:
        """A pre-encoded frame (the drives' TPDOs): no frame built per send."""
        try:
            self._writer.send_message(msg)
        except can.CanError as exc:
            self._send_failed(msg.arbitration_id, exc)

    def _send_failed(self, cob_id: int, exc: can.CanError) -> None:
        self.send_errors += 1
        if self.send_errors in (1, 10, 100, 1000):
            log.warning("simulated segment: send of 0x%03X failed (%d so far): %s",
                        cob_id, self.send_errors, exc)

    def judge_at(self, deadline: float) -> float | None:
        """None once every frame that arrived before ``deadline`` has been handled (a timeout
        at ``deadline`` may be judged now); otherwise when to look again."""
        if self.received_until >= deadline:
            return None
        return max(deadline, self.clock() + RX_IDLE)

    def set_rpdo_routes(self, node_id: int, routes: dict[int, Route]) -> None:
        self._nodes.set_rpdo_routes(node_id, routes)

    # ------------------------------------------------------------------ receiving
    def _receive_loop(self) -> None:
        reader = FrameReader(self.bus)
        while not self._stopped.is_set():
            if not self.pump(reader, RX_IDLE):
                self._stopped.wait(RX_IDLE)

    def pump(self, reader: FrameReader, timeout: float) -> bool:
        """Handle the frames waiting on the bus (after up to ``timeout`` s for the first).
        False when the bus failed (counted in ``bus_errors``) or the read raised anything
        else (recorded in ``errors``): read it again a little later.

        A segment whose SYNC steps are left to its group stops after a SYNC it defers and
        keeps the frames after it (``backlog``) for the next pump: a group that lags a few
        cycles then catches up one cycle of every bus at a time, each with one joined step,
        instead of every segment stepping alone at its next SYNC, which costs four times
        as much and keeps it lagging."""
        before = self.clock()
        ok = True
        batch, self._backlog = self._backlog, []
        if batch:
            complete = False  # read earlier: the bus may hold more
        else:
            try:
                batch = reader.read(timeout, RX_BATCH)
            except can.CanError as exc:  # the interface: down, gone, closed
                if not self._stopped.is_set():  # stopping closes the bus: not a failure
                    self._bus_failed(exc)
                batch = []  # a failed interface delivers nothing: consumers may time out
                ok = False
            except Exception as exc:  # noqa: BLE001 - a bug: check() says so, receiving goes on
                self.record(exc)
                batch = []
                ok = False
            else:
                if self.bus_errors and self._bus_down:
                    self._bus_down = False
                    log.warning("simulated segment: the bus reads again (after %d failed "
                                "reads)", self.bus_errors)
            complete = len(batch) < RX_BATCH
        now = self.clock()
        offset = clock_offset()
        with self.lock:
            arrived = now
            for k, msg in enumerate(batch):
                if msg.is_error_frame or msg.is_extended_id:
                    continue
                arrived = to_monotonic(offset, msg.timestamp, now)
                if msg.is_remote_frame:  # node guarding: the only remote request a drive takes
                    guarded = self.drives.get(msg.arbitration_id - c301.HEARTBEAT)
                    if guarded is not None:
                        guarded.on_guard_request(arrived)
                    continue
                try:
                    self._dispatch(msg.arbitration_id, bytes(msg.data), arrived)
                except Exception as exc:  # noqa: BLE001 - keep the segment receiving
                    self.record(exc)
                if self.deferred_dt is not None and k + 1 < len(batch):
                    self._backlog = batch[k + 1:]  # after the group's step
                    complete = False
                    break
            # read until empty: everything that arrived before the read began is handled
            self.received_until = before if complete else arrived
        return ok

    @property
    def backlog(self) -> bool:
        """Frames read but not handled yet: they come after a SYNC whose step is deferred."""
        return bool(self._backlog)

    def nothing_arrived(self, since: float) -> None:
        """The bus had no frame waiting when a wait that began at ``since`` ended (a
        SegmentGroup's selector said so): everything that arrived before it is handled.
        Called by the group's thread only, the one writer of ``received_until`` then, so
        without the lock (the timers only read it). As with ``pump``, a frame is judged by
        its arrival stamp: an in-process bus stamps a frame just before delivering it, so a
        sender stalled between the two can deliver one stamped a little before ``since``;
        the consumer times' margins cover such a stall, as they cover a slow reader."""
        if since > self.received_until:
            self.received_until = since

    def _dispatch(self, cob_id: int, data: bytes, arrived: float) -> None:
        if self.deferred_dt is not None and not (
                c301.HEARTBEAT < cob_id <= c301.HEARTBEAT + 0x7F):
            # this frame comes after the SYNC: step first (a heartbeat needs no step: a
            # master sends its heartbeat right after its SYNC, and only its arrival counts)
            self._finish_deferred_or_record()
        if cob_id == c301.NMT:
            if len(data) >= 2:
                for node, drive in list(self.drives.items()):  # a reset may move a node
                    if data[1] in (0, node) and not self._nodes.reset_moves(node, data[0]):
                        drive.on_nmt(data[0])
            self.nmt_count += 1
            return
        if cob_id == LSS_REQUEST:
            for slave in self.lss_slaves:
                slave.on_request(data)
            return
        if cob_id == c301.SYNC:
            self._on_sync(arrived)
            return
        route = self._nodes.fixed.get(cob_id)
        if route is not None:
            route(data)
            return
        rpdo = self._nodes.rpdo.get(cob_id)
        if rpdo is not None:
            rpdo(data)
            return
        if c301.HEARTBEAT < cob_id <= c301.HEARTBEAT + 0x7F and data:
            for drive in self.drives.values():
                drive.on_heartbeat(cob_id - c301.HEARTBEAT, arrived)

    # ------------------------------------------------------------------ joints
    def _on_sync(self, arrived: float) -> None:
        dt = self._prepare(on_sync=True, now=arrived)
        if self._defer_steps:
            self.deferred_dt = dt
            self._deferred_at = self.clock()
            return
        self.dynamics.step(dt)
        self._finish(on_sync=True)

    def defer_steps(self) -> None:
        """From now on a SYNC's dynamics step waits for this segment's group (before start)."""
        self._defer_steps = True

    def finish_deferred(self) -> None:
        """Take the deferred step alone, then sample and answer the SYNC (lock held)."""
        dt, self.deferred_dt = self.deferred_dt, None
        if dt is not None:
            self.dynamics.step(dt)
            self._finish(on_sync=True)

    def finish_joined(self) -> None:
        """The group stepped this segment's joints with the others': sample and answer."""
        if self.deferred_dt is not None:
            self.deferred_dt = None
            self._finish(on_sync=True)

    def _step(self, on_sync: bool, now: float) -> None:
        self.dynamics.step(self._prepare(on_sync, now))
        self._finish(on_sync)

    def _prepare(self, on_sync: bool, now: float) -> float:
        """The step's length; the drives apply their RPDOs and command their joints."""
        last = self._last_step if self._last_step is not None else now
        if on_sync and self.sync_period is not None:
            dt = self.sync_period
        else:  # a SYNC that arrived before a free-running step was handled: no step back
            dt = min(max(now - last, 0.0), self.max_dt)
        self._last_step = max(now, last)
        for drive in self.drives.values():
            drive.prepare_step(dt, on_sync)
        return dt

    def _finish(self, on_sync: bool) -> None:
        """After the step: the drives sample and send their TPDOs."""
        dyn = self.dynamics
        position, velocity, torque = (dyn.position.tolist(), dyn.velocity.tolist(),
                                      dyn.torque.tolist())
        for drive in self.drives.values():
            drive.finish_step(on_sync, position, velocity, torque)
        if on_sync:
            self.sync_count += 1

    def _free_run(self) -> None:
        period = self.free_run_period
        assert period is not None  # scheduled only when free running is on
        now = self.clock()
        # Free-run only over a silence the reader has seen (give or take the two RX_IDLE
        # an idle reader's received_until may be old): a receive thread that lags has
        # SYNCs queued, and a long step here (up to max_dt in sub-steps, under the lock)
        # would only make it lag more.
        if (self._last_step is None or now - self._last_step >= period) \
                and self.received_until >= now - period - 2 * RX_IDLE:
            self._step(on_sync=False, now=now)
        self.schedule(now + period, self._free_run)

    def _run_timer(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        if self._stopped.is_set():
            return
        try:
            with self.lock:
                if self.deferred_dt is not None:  # a SYNC's step waits for the group's
                    if self.clock() - self._deferred_at < RX_IDLE:
                        # it comes within JOIN_WAIT: this event after it, not a step alone
                        # (several times the cost of a joined one) taken now for it
                        self.schedule(self.clock() + JOIN_WAIT, fn, *args)
                        return
                    self._finish_deferred_or_record()  # the group's thread is stuck
                fn(*args)
        except Exception as exc:  # noqa: BLE001 - keep the timers running
            self.record(exc)

    def run_due_timers(self, now: float) -> None:
        """A lockstep pass (group.py) runs the timer events due by ``now`` on its thread,
        unless the lock is taken (then at a later pass); the timer thread stands by."""
        if not self.lock.acquire(blocking=False):
            return
        try:
            self._timers.run_due(now)
        finally:
            self.lock.release()

    def finish_pending_step(self) -> None:
        """Take a SYNC's step now if it waits for the group (lock held): a fault injected
        through the drive's API comes after the SYNC whose RPDOs the drive applied."""
        if self.deferred_dt is not None:
            self._finish_deferred_or_record()

    def _finish_deferred_or_record(self) -> None:
        """The deferred step, taken now because an event for the drives comes after it; a
        failure is recorded, and the event is still handled."""
        try:
            self.finish_deferred()
        except Exception as exc:  # noqa: BLE001 - the event is still this one's to handle
            self.deferred_dt = None
            self.record(exc)

    def _bus_failed(self, exc: BaseException) -> None:
        self.bus_errors += 1
        self.bus_error = exc
        if not self._bus_down or self.bus_errors % 10000 == 0 \
                or self.bus_errors in (10, 100, 1000):
            self._bus_down = True
            log.warning("simulated segment: reading the bus failed (%d so far), reading "
                        "again every %.0f ms: %s", self.bus_errors, RX_IDLE * 1000, exc)

    def record(self, exc: BaseException) -> None:
        """A failure of the simulation itself: kept (the first 100) for check(), logged."""
        if len(self.errors) < 100:
            self.errors.append(exc)
        log.error("simulated segment: %r", exc, exc_info=exc)

    def status_lines(self) -> list[str]:
        """One line per axis of every drive."""
        with self.lock:
            return [line for d in self.drives.values() for line in d.status_lines()]
