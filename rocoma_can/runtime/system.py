"""The whole system ``rocoma-can run`` starts from a RuntimeConfig: the drives' hardware layer,
the manager with its controllers (built here: nothing in drivers/ builds a manager), the
manager's CANopen node, and the loop."""
from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from ..audit import Audit
from ..controllers.torque_off import TorqueOff
from ..drivers.cycle.status import HardwareStatus
from ..drivers.hardware import CanopenHardware
from ..drivers.link.bus import open_bus
from ..fleet.bridge import FleetBridge, FleetError
from ..fleet.config import FleetConfig
from ..inputs import TopicCommanded
from ..live.foxglove import FoxgloveConfig, FoxgloveView
from ..manager import ControllerManager
from ..node.objects import RESULT_NAMES
from ..node.server import ManagerNode
from ..plugins import add_to_manager
from ..record.recorder import BusToRecord, FlightStatus, Recorder, RecordingStatus
from ..record.trace import SignalTrace
from ..ros2.node import Ros2Error, Ros2Node
from .another_manager import refuse_if_heard
from .config import RuntimeConfig
from .loop import ControlLoop, TimingSummary

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CycleReport:
    """The loop's cycle statistics in a status report (ms; None: no cycle yet)."""
    rate: float
    cycles: int
    overruns: int
    overruns_waiting: int       # of those, off the CPU longer than on it (CycleStats.record)
    period_mean_ms: float | None
    period_max_ms: float | None
    jitter_p99_ms: float | None
    work_max_ms: float | None
    #: times a yield of the loop's spin cost it a period and it stopped yielding a while
    spin_pauses: int = 0


@dataclass(frozen=True)
class RuntimeStatus:
    """The hardware's status with what the running system adds; typed until ``as_dict``
    makes the JSON shape 0x2140, ``status --json`` and the Zenoh status query serve."""
    hardware: HardwareStatus
    loads: dict[str, float]   # per bus: planned load at the running rate (0..1)
    cycle: CycleReport
    zenoh: dict[str, Any] | None
    ros2: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        report = self.hardware.as_dict()
        for bus in report["buses"]:
            bus["load"] = self.loads.get(bus["name"])
        report["cycle"] = dict(vars(self.cycle))  # (plain values: no deep copy)
        if self.zenoh is not None:
            report["zenoh"] = self.zenoh
        if self.ros2 is not None:
            report["ros2"] = self.ros2
        return report


def manager_for(hardware: CanopenHardware, **kwargs: Any) -> ControllerManager:
    """A ControllerManager over a CanopenHardware, wired to it: TorqueOff as the failproof
    layer, the hardware's ``limit_command`` (modes, NaN, limits), ``neutral_command`` (on
    every fall to a lower layer) and ``send_torque_off`` (on a hung update), and its fault
    events reach it through the loop (``runtime.loop.run_cycle``): the hardware never
    holds the manager.

    The failproof layer is not configurable: passing ``failproof`` is a TypeError. The
    torque-off frames in FAILPROOF do not depend on it anyway (drivers/hardware.py).
    """
    if "failproof" in kwargs:
        raise TypeError("the CAN hardware layer always installs TorqueOff as failproof "
                        "controller; it cannot be replaced")
    for own in ("limit_command", "reset_command"):
        if own in kwargs:
            raise TypeError(f"{own} is the hardware's own (modes, NaN, limits; a neutral "
                            "command on every fall to a lower layer)")
    kwargs.setdefault("on_hang", hardware.send_torque_off)
    kwargs.setdefault("switch_guard", hardware.not_ready)  # every drive ready to switch
    manager = ControllerManager(TorqueOff(), hardware.dt, hardware.state, hardware.command,
                                limit_command=hardware.limit_command,
                                reset_command=hardware.neutral_command, **kwargs)
    return manager


class Runtime:
    """Everything ``rocoma-can run`` starts from a RuntimeConfig, in start-up order:
    the drives' hardware layer, the manager with the configured controllers, the manager's
    CANopen node (on a second handle of its bus, `manager.bus`), and the loop. E-stop frames
    are the hardware's, on every bus, in the cycle (the node owns the COB-ID, 0x2130)."""

    def __init__(self, config: RuntimeConfig, *,
                 on_cycle: Callable[[float], None] | None = None,
                 record: str | None = None, flight: str | None = None,
                 flight_seconds: float = 10.0,
                 announce: Callable[[str], None] | None = None,
                 foxglove: FoxgloveConfig | None = None) -> None:
        """``record``: a directory for every frame and cycle (record/recording.py); ``flight``:
        the flight recorder's directory (None: off), keeping ``flight_seconds``;
        ``announce``: told each flight record's path (``rocoma-can run`` prints it).
        ``config.fleet`` serves the manager on Zenoh (fleet/bridge.py): FleetError when Zenoh
        cannot be used and the section says ``required``; otherwise a warning, and the
        reason in the status report. ``foxglove``: the live view (live/foxglove.py;
        FoxgloveError when it cannot be served)."""
        self.config = config
        self.recorder: Recorder | None = None
        self.recording: RecordingStatus | None = None
        self.flight: FlightStatus | None = None
        self.fleet: FleetBridge | None = None
        self.ros2: Ros2Node | None = None
        self.ros2_error = ""
        self.foxglove: FoxgloveView | None = None
        self.fleet_error = ""
        self._recovery_lock = threading.Lock()
        self._recovery_told: Future[bool] | None = None
        self._recovery_cut: Future[bool] | None = None
        m = config.manager
        self.hardware = CanopenHardware({b.label: b for b in config.buses}, config.drives,
                                        m.node_id, config.dt,
                                        manager_heartbeat_ms=m.heartbeat_ms,
                                        supervision=config.supervision,
                                        estop_cob_id=m.estop_cob_id)
        # built in order; on a failure, what was built so far is closed (_close_parts)
        self._parts: list[Callable[[], object]] = [self.hardware.close]
        try:
            # before anything is built that sends: another manager on these buses is
            # BusTaken (runtime/another_manager.py), and nothing was sent
            refuse_if_heard(config, self.hardware.layouts)
            names = [d.name for d in config.drives]
            required = (None if m.required_drives is None
                        else [names.index(n) for n in m.required_drives])
            hardware = self.hardware
            self.manager = manager_for(
                hardware, estop_must_be_cleared=m.estop_must_be_cleared,
                timing=config.timing,
                switch_guard=lambda: hardware.not_ready(required))
            self._parts.insert(0, self.manager.shutdown)
            self.manager.subscribe(Audit())  # its events as the audit trail's lines
            add_to_manager(self.manager, config.controllers)
            bus = config.node_bus
            extra: dict[str, object] = {"fd": True} if bus.fd else {}
            if bus.data_bitrate is not None:
                extra["data_bitrate"] = bus.data_bitrate
            self._node_bus = open_bus(bus.interface, bus.channel, bus.bitrate,
                                      receive_own_messages=False, **extra)
            self._parts.append(self._node_bus.shutdown)
            self.node = ManagerNode(self.manager, m.node_id, self._node_bus,
                                    estop_cob_id=m.estop_cob_id, status_period=m.status_period,
                                    recover=self._recover, home=self._home,
                                    heartbeat_ms=m.heartbeat_ms,
                                    drive_status=self.status_report,
                                    estop_in_cycle=hardware.set_estop_cob_id,
                                    bitrate=bus.bitrate)
            self._parts.insert(0, self.node.close)
            if foxglove is not None:  # served by the writer process (_recorders)
                self.foxglove = FoxgloveView(foxglove, self.manager, self.status,
                                             recover=self._recover, robot=config.robot)
                self._parts.insert(0, self.foxglove.close)
            self.loop = ControlLoop(self.hardware, self.manager, config.rate,
                                    priority=config.priority, cpus=config.cpus,
                                    on_cycle=on_cycle, spin=config.spin)
            # after the loop: the recorder's status reports read its statistics
            self.loop.trace = self._recorders(record, flight, flight_seconds, announce)
            if config.fleet is not None:  # its queries read the loop's statistics
                self._bridge(config.fleet)
            if config.ros2 is not None:
                self._ros2_node()
            else:
                for name, adapter in self.manager.adapters().items():
                    if isinstance(adapter.controller, TopicCommanded):
                        log.warning("controller %r follows %s, but no ROS 2 node runs (run "
                                    "--ros2 or a ros2: section): switched to, it fails when "
                                    "its timeout passes", name,
                                    adapter.controller.command_topic)
        except BaseException:
            self.close()
            raise

    def _bridge(self, fleet: FleetConfig) -> None:
        try:
            self.fleet = FleetBridge(fleet, self.manager, self.status,
                                     recover=self._recover,
                                     cycles=lambda: self.loop.stats.cycles)
        except FleetError as exc:
            if fleet.required:
                raise
            self.fleet_error = str(exc)
            log.warning("running without Zenoh (zenoh.required: false): %s", exc)
            return
        self._parts.insert(0, self.fleet.close)

    def _ros2_node(self) -> None:
        """The ROS 2 node (ros2/node.py): Ros2Error when it cannot be served and the section
        says ``required``; otherwise a warning, and the reason in the status report. The
        controllers that follow a command topic get its commands."""
        config = self.config
        assert config.ros2 is not None
        inputs = [a.controller for a in self.manager.adapters().values()
                  if isinstance(a.controller, TopicCommanded)]
        first = config.buses[0].label
        try:
            self.ros2 = Ros2Node(config.ros2, self.manager, self.hardware.state, self.status,
                                 recover=self._recover, inputs=inputs,
                                 buses={d.name: d.bus or first for d in config.drives})
        except Ros2Error as exc:
            if config.ros2.required:
                raise
            self.ros2_error = str(exc)
            log.warning("running without the ROS 2 node (ros2.required: false): %s", exc)
            return
        self._parts.insert(0, self.ros2.close)

    def _recorders(self, record: str | None, flight: str | None, seconds: float,
                   announce: Callable[[str], None] | None) -> SignalTrace | None:
        """The flight recorder, --record and the live view: rings the loop and the
        hardware's buses fill, and the writer process that writes and serves them
        (record/recorder.py)."""
        if record is None and flight is None and self.foxglove is None:
            return None
        config = self.config
        recorder = self.recorder = Recorder(
            self.hardware.state, self.hardware.command, self.manager, config.rate,
            [BusToRecord(b.label, b.channel, b.fd) for b in config.buses], record=record,
            flight=flight, seconds=seconds, controllers=list(self.manager.adapters()),
            robot=config.robot, announce=announce, view=self.foxglove,
            loop_cpus=config.cpus or ())
        self.flight, self.recording = recorder.flight, recorder.recording
        # closed after the manager's shutdown, which delivers its last events (the loop's
        # stop) to it: what it writes ends with how it ended
        self._parts.insert(self._parts.index(self.manager.shutdown) + 1, recorder.close)
        self.manager.subscribe(recorder.on_event)
        recorder.status_source = self.status
        if recorder.frame_taps:
            self.hardware.record_frames(recorder.frame_taps)
        return recorder.trace

    def _recover(self) -> Future[bool]:
        """The drives' recovery (hardware.recover) for the node, Zenoh and Foxglove alike,
        each one told to the manager's subscribers as it starts and as it ends (the
        recording's /rocoma/event, the log lines live and recorded). A request while one
        runs joins it, told once."""
        with self._recovery_lock:  # (callers' threads only; the cycle never takes it)
            future = self.hardware.recover()
            if future is self._recovery_told:
                return future
            self._recovery_told = future
        self.manager.notify_recovery("started")
        future.add_done_callback(self._recovery_ended)
        return future

    def _recovery_ended(self, future: Future[bool]) -> None:
        """Resolved on the cycle thread (or by the hardware's close): one queued event."""
        if future is self._recovery_cut:  # told by close(), while the manager listened
            return
        self.manager.notify_recovery(
            "done: every drive is back, the e-stop latch is cleared" if future.result()
            else "failed: not every drive came back in time (status says which)")

    def _cut_recovery(self) -> None:
        """A recovery still running as the runtime closes: told now, while the manager and
        the recording still take events (the hardware's close, last, ends it)."""
        with self._recovery_lock:
            future = self._recovery_told
            if future is None or future.done():
                return
            self._recovery_cut = future
        self.manager.notify_recovery("failed: the run stopped before it ended")

    def _home(self, drive: str) -> Future[str]:
        """The node's home service: judged on the manager's state now, not the last cycle's
        (a switch that has just committed is OK before the hardware hears of it)."""
        return self.hardware.home(drive, manager_state=self.manager.state)

    def status_report(self) -> RuntimeStatus:
        """What the manager node serves as 0x2140 (``rocoma-can status``): the hardware's
        report (start-up, recovery, buses, drives), each bus's planned load at the running
        rate, and the loop's cycle statistics (over its last 4096 cycles)."""
        rate = self.config.rate
        loads = {name: round(planned.bits_per_cycle * rate / planned.bitrate, 4)
                 for name, planned in self.config.loads.items()}
        t = self.loop.stats.summary()
        mean, peak, p99, work = (round(v * 1e3, 3) if math.isfinite(v) else None
                                 for v in (t.period_mean, t.period_max, t.jitter_p99,
                                           t.work_max))
        zenoh = (self.fleet.info() if self.fleet is not None
                 else {"error": self.fleet_error} if self.fleet_error else None)
        ros2 = (self.ros2.info() if self.ros2 is not None
                else {"error": self.ros2_error} if self.ros2_error else None)
        return RuntimeStatus(self.hardware.status_report(), loads,
                             CycleReport(rate, t.cycles, t.overruns, t.overruns_waiting,
                                         mean, peak, p99, work, self.loop.yield_pauses),
                             zenoh, ros2)

    def status(self) -> dict[str, Any]:
        """What ``rocoma-can status --json`` prints, built here rather than read over SDO
        (the Zenoh status query answers with it)."""
        m, node = self.manager, self.node
        report = self.status_report().as_dict()
        return {"state": m.state.name, "active": m.active_controller_name,
                "latched": m.estop_latched,
                "last_switch": RESULT_NAMES.get(node.last_result, "?"),
                "switch_refused": m.last_refusal, "estop_cause": node.last_cause,
                "estop_cob_id": node.estop_cob_id,
                **{k: report.get(k) for k in ("startup_finished", "recovery", "bus_fault",
                                              "cycle", "buses", "drives", "zenoh",
                                              "ros2")},
                **({"foxglove": self.foxglove.info()} if self.foxglove is not None else {})}

    def run(self, duration: float | None = None, signals: bool = True) -> TimingSummary:
        """Start the bus side, run the loop until stopped, torque-off; the caller closes."""
        restore = self.loop.install_signal_handlers() if signals else None
        try:
            self.hardware.start()
            self.node.start()
            if self.fleet is not None:
                self.fleet.start()
            if self.ros2 is not None:
                self.ros2.start()
            if self.foxglove is not None:
                self.foxglove.start()
            return self.loop.run(duration)
        finally:
            if self.fleet is not None:
                self.fleet.loop_stopped()
            if self.ros2 is not None:
                self.ros2.loop_stopped()
            if self.foxglove is not None:
                self.foxglove.loop_stopped()
            if restore is not None:
                restore()

    def close(self) -> None:
        """Node, manager threads, hardware (joins its bus reader), then the node's bus.
        A Ctrl-C during one part (an impatient second one) still closes the others, then
        goes on up."""
        self._cut_recovery()  # (none before the runtime was whole: nothing to tell)
        parts, self._parts = self._parts, []
        interrupted: BaseException | None = None
        for close in parts:
            try:
                close()
            except Exception:  # one part's failure must not leave the others running
                log.exception("closing %r failed", close)
            except BaseException as exc:  # KeyboardInterrupt, SystemExit: after the rest
                interrupted = interrupted or exc
        if interrupted is not None:
            raise interrupted

    def __enter__(self) -> Runtime:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
