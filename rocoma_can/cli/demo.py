"""``rocoma-can demo``: the whole system on in-process CAN buses.

Simulated CiA 402 drives (in a process of their own or stepped by the loop: demo_sim.py),
the control loop with the manager and its CANopen node, and an "operator" that talks to the
manager only the way another CAN node would (SDO and raw frames). The walk-through:
bring-up, clear, switch to pd, switch to trajectory (bumpless, by swap state), a drive
fault -> emergency controller (damp), a second fault -> failproof torque-off, recovery of
the drives, a switch back to pd, an e-stop by a raw CAN frame, and the SIGTERM-like stop of
the loop, which ends in torque-off frames. Each step checks what it should; the exit code
is 0 only when every step did. An operator's e-stop (Foxglove, Zenoh, ``rocoma-can
estop``) ends the walk-through early with the robot left stopped (OutsideStop). The
command records the run (every frame, every cycle, every manager event) and plots it, and
prints where both went.
"""
from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import shutil
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from ..cli_args import count, positive, rt_priority, seconds
from ..drivers.protocol.wire import MAX_DATA_BITRATE
from ..errors import ConfigError, RocomaError, SimulatorFailed
from ..events import ManagerState
from ..exit_codes import FAILED, INTERRUPTED, OK, PIPE_CLOSED, USAGE
from ..node.client import ManagerClient
from ..node.objects import ESTOP_CAUSE, STATE_NAMES
from ..record.can_log import RecordingError
from .console import ThreadedLines
from .demo_config import (
    DEFAULT_INTERFACE,
    ESTOP_COB_ID,
    FD_BITRATE,
    FD_DATA_BITRATE,
    MANAGER_ID,
    MIN_PAUSE,
    PAUSES,
    ZENOH_PREFIX,
    default_buses,
    demo_config,
    demo_urdf,
    emulate,
)
from .demo_probe import TorqueOffProbes
from .demo_report import (
    Report,
    Said,
    Step,
    grouped_notes,
    plot_run,
    recording_stopped,
    status_lines,
    summary,
)
from .demo_sim import (
    SIM_CHOICES,
    DemoSimulator,
    InProcessSim,
    SimProcess,
    check_choice,
)
from .demo_stops import Ended, LoopStopped, OutsideStop, loop_running

#: the demo's flight recorder window, s: run keeps 10, but e-stops within half a window make
#: one record, and the walk-through's come seconds apart
FLIGHT_SECONDS = 2.0

if TYPE_CHECKING:  # imported by run_demo(): `rocoma-can --help` must not import them
    from ..live.foxglove import FoxgloveConfig
    from ..ros2.config import Ros2Config
    from ..runtime.config import RuntimeConfig
    from ..runtime.system import Runtime


def _only(cob_ids: set[int]) -> list[can.typechecking.CanFilter]:
    """Filters that pass these 11-bit COB-IDs only."""
    return [{"can_id": c, "can_mask": 0x7FF, "extended": False} for c in sorted(cob_ids)]


class _Watch:
    """Called by the loop every cycle: remembers when the manager state changed (cheap)."""

    def __init__(self) -> None:
        self.changes: list[tuple[float, int, int]] = []  # (time, cycle, new state)
        self.state = -1
        self.cycle = 0
        self.runtime: Runtime | None = None  # set once the runtime exists, before it runs

    def __call__(self, now: float) -> None:
        self.cycle += 1
        assert self.runtime is not None
        state = int(self.runtime.loop.last_state)
        if state != self.state:
            self.state = state
            self.changes.append((now, self.cycle, state))

    def first_change_since(self, mark: int, to: set[int]) -> tuple[float, int] | None:
        """The first change into a state of ``to`` among those recorded after the first
        ``mark`` (len(changes) before the event): by position, not by time, since the cycle
        that reacts may have begun (its ``now``) just before the event and read it."""
        for t, cycle, state in self.changes[mark:]:
            if state in to:
                return t, cycle
        return None


class _Pace:
    """Ends the walk-through ``duration`` s after it began: each pause lasts until its share
    of the duration (PAUSES) has passed, so what bring-up and recovery take comes out of the
    pauses instead of adding to them. Steps slower than their share make it longer."""

    def __init__(self, duration: float, stop: threading.Event) -> None:
        self.start = time.monotonic()
        self.duration = duration
        self.stop = stop
        self.done = 0.0

    def pause(self, share: float) -> None:
        self.done += share
        until = self.start + self.duration * self.done / sum(PAUSES)
        self.stop.wait(max(MIN_PAUSE * share, until - time.monotonic()))


def _wait(predicate: Callable[[], bool], timeout: float, stop: threading.Event) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not stop.is_set():
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def _operator(rt: Runtime, sim: DemoSimulator, client: ManagerClient, watch: _Watch,
              probes: TorqueOffProbes, report: Report, duration: float,
              stop: threading.Event, outside: OutsideStop,
              say: Callable[[str], None]) -> None:
    hw, mgr = rt.hardware, rt.manager
    dt = rt.config.dt
    pace = _Pace(duration, stop)
    pauses = iter(PAUSES)

    def hold() -> None:
        pace.pause(next(pauses))
        loop_running(rt.loop.stop_reason)
        outside.go_on()

    def step(name: str, ok: bool, detail: str = "") -> bool:
        loop_running(rt.loop.stop_reason)  # a step the loop's stop cut short is not judged
        outside.go_on()  # nor one an operator's stop cut short
        report.steps.append(Step(name, ok, detail))
        say(report.steps[-1].line())
        return ok

    def state() -> int:
        return int(mgr.state)

    def reached(what: str, t0: float, mark: int, to: set[int], timeout: float) -> bool:
        """Whether the loop's state went into ``to`` after the event (within ``timeout``),
        as the loop's watch recorded it, and then its latency. Judged by the watch, not by
        the manager's state: the watch runs after the cycle's write and the simulator's
        step, so on a loaded host the manager's state could already show the change the
        watch had not yet recorded, and the latency went missing."""
        hit: tuple[float, int] | None = None

        def seen() -> bool:
            nonlocal hit
            hit = watch.first_change_since(mark, to)
            return hit is not None

        if not _wait(seen, timeout, stop) or hit is None:
            return False
        took = max(0.0, hit[0] - t0)  # the reacting cycle may have begun just before
        report.latencies.append((what, took, max(1, round(took / dt))))
        return True

    try:
        def failed() -> bool:  # a drive that failed start-up ends the wait at once
            return any(d.phase == "FAILED" for d in hw.drive_status())
        _wait(lambda: hw.all_ready or failed(), 30.0, stop)
        if not step("bring-up", hw.all_ready,
                    f"{len(hw.drives_config)} drives configured, mapped and started"
                    if hw.all_ready else hw.not_ready() or "drives not ready"):
            return
        outside.go_on(mgr.estop_requested)  # (before a command that could undo a stop)
        client.write(0x2112, 1)  # clear: must-clear starts latched, like an e-stop button
        result = client.switch("pd")
        if not step("switch to pd (SDO 0x2100)",
                    result == 0 and _wait(lambda: hw.all_enabled, 3.0, stop),
                    f"result {result}, drives enabled: {hw.all_enabled}"):
            return
        hold()
        result = client.switch("trajectory")
        step("switch pd -> trajectory (swap state)", result == 0 and state() == 2,
             f"result {result}, active {mgr.active_controller_name}")
        hold()

        def fault(node: int, becomes: str, target: int) -> bool:
            """Trip a drive's fault; whether the manager reached ``target`` in time."""
            mark = len(watch.changes)
            t0 = sim.trip_fault(node)
            return reached(f"drive {node} fault -> {becomes}", t0, mark, {target}, 2.0)

        node = sim.node_ids[min(2, len(sim.node_ids) - 2)]  # not the last: that one is next
        ok = fault(node, "EMERGENCY", 1)
        step(f"fault on drive {node} -> emergency controller", ok,
             f"state {STATE_NAMES[state()]}, active {mgr.active_controller_name}")
        hold()

        node2 = sim.node_ids[-1]
        if node2 == node:
            step("second fault -> failproof torque-off", True,
                 "skipped: one drive, and it is faulted already")
            mgr.failproof_stop("demo: the step the second fault would have shown")
        else:
            ok = fault(node2, "FAILPROOF", 0)
            step(f"second fault on drive {node2} -> failproof torque-off", ok,
                 f"state {STATE_NAMES[state()]}")
        hold()

        outside.go_on(mgr.estop_requested)
        client.write(0x2113, 1)  # recover drives; on success the e-stop latch is cleared
        # done when the switch guard says so: the recovery clears the latch a moment before
        # it reports its own end, and a switch in between is refused ("a recovery is in
        # progress")
        ok = _wait(lambda: hw.not_ready() is None and not mgr.estop_latched, 8.0, stop)
        step("recovery (SDO 0x2113)", ok, f"drives ready: {hw.all_ready}, "
                                          f"latched: {mgr.estop_latched}"
             + ("" if ok else f"; {hw.not_ready() or 'not ready'}"))
        result = client.switch("pd")
        step("final switch to pd", result == 0 and state() == 2
             and _wait(lambda: hw.all_enabled, 3.0, stop), f"result {result}")
        hold()

        mark, t0 = len(watch.changes), time.monotonic()
        client.bus.send(can.Message(arbitration_id=ESTOP_COB_ID, data=b"\x01",
                                    is_extended_id=False))
        ok = reached(f"CAN e-stop frame 0x{ESTOP_COB_ID:03X} -> EMERGENCY", t0, mark, {1}, 2.0)
        step(f"e-stop by a raw CAN frame on 0x{ESTOP_COB_ID:03X}", ok,
             f"state {STATE_NAMES[state()]}, cause {client.read_text(ESTOP_CAUSE)!r}")
        hold()
    except Ended as ended:
        # the stop is heard a cycle late (the event thread): a command the walk-through
        # gave meanwhile (clear and switch) may have undone it; it is given again
        if mgr.state is ManagerState.OK or not mgr.estop_latched:
            mgr.emergency_stop(cause=f"demo: {ended}, again (a command of the walk-through "
                                     "came with it)")
        report.steps.append(Step("walk-through", True, f"ended early by an e-stop from "
                                 f"outside it ({ended}): the robot stays stopped, the "
                                 f"steps after it not run"))
        say(f"ok  walk-through: {report.steps[-1].detail}")
    except LoopStopped as stopped:
        signalled = str(stopped).startswith("signal ")
        if signalled:
            report.interrupted = str(stopped)
        report.steps.append(Step("walk-through", signalled, f"cut short: the loop stopped "
                                 f"({stopped}); the steps after it not run"))
        say(f"{'stop' if signalled else 'FAILED'} walk-through: {report.steps[-1].detail}")
    except Exception as exc:  # an SDO failure is a failed step, and the demo ends
        why = ""
        try:  # a refused switch says why (0x2103); a fault, its cause (0x2124)
            why = f"; refusal: {client.read_text(0x2103)!r}; state {STATE_NAMES[state()]}, " \
                  f"cause {client.read_text(ESTOP_CAUSE)!r}"
        except Exception:  # noqa: BLE001 - the report is best effort
            pass
        report.steps.append(Step("operator", False, f"{type(exc).__name__}: {exc}{why}"))
        say(f"FAILED operator: {report.steps[-1].detail}")
    finally:
        # the probes' buses open: the stop's torque-off frames wait in their queues
        probes.arm(rt.loop.stop_reason or None)
        report.walk_time = time.monotonic() - pace.start
        rt.loop.stop("walk-through finished")


def _load_line(config: RuntimeConfig) -> str | None:
    """What the buses carry as the buses they stand for: the load of CAN FD ones (--fd:
    checked, as for real buses), or, where in-process buses without a bit rate carry what
    a real classic 1 Mbit/s bus would not, a note that says so (and what fits)."""
    if config.loads:
        busiest = max(config.loads.values(), key=lambda planned: planned.load)
        return (f"rocoma-can demo: the busiest bus: {busiest.explain()} "
                f"({busiest.frames_per_cycle} frames a cycle)")
    from ..runtime.bus_load import bus_load
    for b in config.buses:
        classic = bus_load([config.plans[d.name].layout for d in config.drives_on(b)],
                           config.rate, FD_BITRATE)
        if classic.load > 1.0:
            return (f"  note: 1 Mbit/s classic buses would not carry this ({b.label}: "
                    f"{classic.explain()}); the in-process ones do (--fd: CAN FD buses, "
                    "checked as real ones)")
    return None


def default_record_dir() -> Path:
    """A new directory per run under the state directory's demo/ (commands.state_dir):
    named for its start, numbered after a run started in the same second (a recording is
    never written over)."""
    from .commands import state_dir
    first = state_dir("demo", time.strftime("%Y%m%d-%H%M%S"))
    path, n = first, 1
    while path.exists():
        n += 1
        path = first.with_name(f"{first.name}-{n}")
    return path



def run_demo(drives: int = 6, rate: float = 200.0, duration: float = 16.0,
             out: Callable[[str], None] = print, buses: int | None = None,
             interface: str = DEFAULT_INTERFACE, eds: str | None = None,
             record: str | Path | None = None, zenoh_listen: str | None = None,
             flight: str | Path | None = None,
             foxglove: FoxgloveConfig | None = None,
             data_bitrate: int | None = None, channel: str | None = None,
             sim: str = "loop", priority: int | None = None,
             ros2: Ros2Config | None = None) -> Report:
    """The walk-through; ``eds``: the simulated drives emulate this EDS/DCF and the demo
    uses the modes it supports, skipping (with the reason) the steps it cannot do;
    ``record``: a directory for the run's recording (``run --record``'s files) and its
    plot ``demo.png``; ``zenoh_listen``: an endpoint the manager serves Zenoh on, under
    the prefix ``rocoma/demo`` (another shell can watch and e-stop it); ``duration``: s
    from the start of bring-up to the loop's stop (_Pace); ``flight``: the flight
    recorder's directory, as ``run`` has it: each e-stop leaves a record there, its path
    said as it is written. Its window is FLIGHT_SECONDS, not run's 10 s: e-stops within
    half a window make one record, and the walk-through's are seconds apart. ``foxglove``:
    the live view, as ``run --foxglove`` serves it. ``data_bitrate``: the buses are CAN FD
    buses (demo_config's FD_BITRATE and this data bit rate): every frame an FD frame with
    bit rate switching, the drives' PDOs up to FD_PDO_BYTES, the load checked as for real
    buses (ConfigError when it does not fit). ``channel``: the in-process channel (several
    buses: ``channel-0``, ...) another part of this process can listen on; default: a new
    one per run. ``sim``: where the simulated drives run, ``loop`` (stepped by the loop's
    thread after each write) or ``process`` (one of their own; demo_sim.py). ``priority``:
    the loop's thread runs SCHED_FIFO at it, as a robot's ``realtime.priority`` has it;
    where the system refuses, the summary says why and the demo runs on at normal
    priority. ``ros2``: the manager as a ROS 2 node, as ``run --ros2`` serves it."""
    from ..drivers.link.bus import open_bus
    from ..live.urdf import parse_urdf
    from ..runtime.config import validate
    from ..runtime.system import Runtime
    emulated = emulate(eds, drives) if eds else None
    if emulated is not None:
        out(f"rocoma-can demo: the drives emulate {eds}: modes {', '.join(emulated.modes)}")
        for note in emulated.notes:
            out(f"  note: {note}")
    buses = default_buses(drives) if buses is None else buses
    channel = channel or f"rocoma-demo-{uuid.uuid4().hex[:8]}"
    fd = data_bitrate is not None
    raw = demo_config(channel, drives, rate, buses, interface, emulated, data_bitrate,
                      priority)
    if zenoh_listen is not None:
        raw["zenoh"] = {"prefix": ZENOH_PREFIX, "listen": [zenoh_listen], "multicast": False}
    config = validate(raw, source="demo")
    config.ros2 = ros2
    config.robot = parse_urdf(demo_urdf([d.name for d in config.drives]).encode(), "demo")
    notes = grouped_notes(config.plans)
    for line in notes.values():
        out(line)
    said_load = _load_line(config)
    if said_load is not None:
        out(said_load)
    report = Report()
    if (record is not None or flight is not None) and importlib.util.find_spec("mcap") is None:
        out("rocoma-can demo: not recording, no flight records: MCAP needs pip install "
            "'rocoma-can[record]'")
        record = flight = None
    watch = _Watch()
    stop = threading.Event()
    sim_buses = [(b.channel, [d.node_id for d in config.drives_on(b)]) for b in config.buses]
    as_fd: dict[str, Any] = {"fd": True} if fd else {}  # SocketCAN: FD frames to FD sockets
    probes = TorqueOffProbes(config, lambda bus, cob_ids: open_bus(
        interface, bus, receive_own_messages=False, can_filters=_only(cob_ids), **as_fd))
    simulator: DemoSimulator | None = None
    client_bus: can.BusABC | None = None
    said = Said(set(notes))  # the hardware logs each drive's notes: said above, grouped
    hardware_log = logging.getLogger("rocoma_can.drivers.hardware")
    hardware_log.addFilter(said)
    try:
        # the drives stepped by the loop, or in a process of their own (demo_sim.py: as a
        # robot's compute in theirs; python-can's virtual bus joins no other process)
        check_choice(sim, interface)
        if sim == "loop":
            in_process = InProcessSim(sim_buses, interface, emulated, fd)
            simulator, on_cycle = in_process, in_process.on_cycle(watch)
        else:
            simulator, on_cycle = SimProcess(sim_buses, eds, drives, fd), watch
        # The client and the probes (demo_probe.py: from the walk-through's end) filter
        # what they read (the interface drops the rest): at 1 kHz every bus carries ~13
        # frames a cycle, and readers of all of it cost the loop's process more CPU than the
        # drives' simulation.
        client_bus = open_bus(interface, config.node_bus.channel, receive_own_messages=False,
                              can_filters=_only({0x580 + MANAGER_ID}), **as_fd)  # SDO answers
        with Runtime(config, on_cycle=on_cycle,
                     record=None if record is None else str(record),
                     flight=None if flight is None else str(flight),
                     flight_seconds=FLIGHT_SECONDS, foxglove=foxglove,
                     announce=lambda text: out(f"rocoma-can demo: {text}")) \
                as rt, ManagerClient(client_bus, MANAGER_ID) as client:
            watch.runtime = rt
            kind = f"{interface} CAN FD" if fd else interface
            on = (f"{kind} bus {config.bus.channel}" if buses == 1
                  else f"{buses} {kind} buses {channel}-0..{buses - 1}")
            out(f"rocoma-can demo: {drives} simulated drives, {rate:g} Hz, manager node "
                f"{MANAGER_ID}, e-stop COB-ID 0x{ESTOP_COB_ID:03X} ({on})")
            out(f"rocoma-can demo: the simulated drives run {simulator.where}")
            if rt.foxglove is not None:
                from ..live.foxglove import describe_view
                out(f"rocoma-can demo: {describe_view(rt.foxglove)}")
            if rt.ros2 is not None:
                from ..ros2.node import describe_node as describe_ros2
                out(f"rocoma-can demo: {describe_ros2(rt.ros2)}")
            if zenoh_listen is not None:
                out(f"rocoma-can demo: on Zenoh as {ZENOH_PREFIX} at {zenoh_listen}; from "
                    f"another shell: rocoma-can status --watch --zenoh {ZENOH_PREFIX} "
                    f"--zenoh-connect {zenoh_listen} --zenoh-no-multicast (estop: the same "
                    "with estop)")
            outside = OutsideStop(stop)
            rt.manager.subscribe(outside)  # (the manager goes with the runtime)
            operator = threading.Thread(
                target=_operator, name="demo-operator",
                args=(rt, simulator, client, watch, probes, report, duration, stop, outside,
                      out))
            status = threading.Thread(target=status_lines, name="demo-status",
                                      args=(rt, stop, out))
            operator.start()
            status.start()
            try:
                timing = rt.run(duration=duration * 3 + 20)
            finally:
                stop.set()
                operator.join(15.0)
                status.join(2.0)
            time.sleep(0.1)  # the probes run on their buses' reader threads
            step = Step("loop stop -> torque-off frames", *probes.judge(
                rt.loop.stop_reason, int(rt.loop.last_state), drives,
                bool(report.interrupted)))
            report.steps.append(step)
            out(step.line())
            if rt.recording is not None and rt.recording.errors:  # (a full disk, the
                recording_stopped(report, rt.recording.errors)   # writer killed)
                out(f"FAILED recording: {rt.recording.errors[0]}")
            summary(out, report, timing, rt)
        if rt.flight is not None:  # closed: the last record is written
            report.flight_records = list(rt.flight.dumps)
            out(f"flight records: {len(report.flight_records)} in {rt.flight.directory}")
        try:
            simulator.check()
        except RuntimeError as exc:  # a drive's bug, or the drives' process died
            report.steps.append(Step("simulated drives", False, str(exc)))
            out(f"FAILED simulated drives: {exc}")
        if record is not None:
            plot_run(Path(record), report, out,
                     rt.recording.errors if rt.recording is not None else ())
    finally:
        hardware_log.removeFilter(said)
        probes.close()
        if client_bus is not None:
            client_bus.shutdown()
        if simulator is not None:
            simulator.stop()
    return report


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "demo", help="run the embedded demo (in-process bus, simulated drives)",
        description=__doc__.split("\n\n")[0])
    p.add_argument("--drives", type=int, default=6, help="simulated drives (default 6)")
    p.add_argument("--buses", type=int, default=None,
                   help="in-process CAN buses the drives are spread over (default: one up to "
                        "6 drives, else one per 3 drives)")
    p.add_argument("--rate", type=positive, default=200.0, help="loop rate, Hz (default 200)")
    p.add_argument("--eds", default=None, metavar="FILE",
                   help="the simulated drives emulate this EDS/DCF: the demo uses the modes "
                        "it supports and says which steps it skips and why")
    p.add_argument("--fd", action="store_true",
                   help="CAN FD buses (1 Mbit/s arbitration, --data-bitrate data phase): FD "
                        "frames both ways, the drives' PDOs up to 64 bytes (one RPDO and one "
                        "TPDO a cycle), the bus load checked as for real buses")
    p.add_argument("--data-bitrate", type=count, default=None, metavar="BIT/S",
                   help=f"the data phase of the --fd buses (default {FD_DATA_BITRATE})")
    p.add_argument("--interface", choices=("inproc", "virtual"), default=DEFAULT_INTERFACE,
                   help="in-process bus: inproc (default; one copy per frame, fit for "
                        "1 kHz) or python-can's virtual (a copy per frame and receiver)")
    p.add_argument("--sim", choices=SIM_CHOICES, default="loop",
                   help="where the simulated drives run: loop (default: stepped by the loop "
                        "after each write) or process (their own, so the loop pays only for "
                        "their frames, as with real drives: for a host with a core for each "
                        "busy process; inproc buses)")
    p.add_argument("--duration", type=seconds, default=16.0,
                   help="the walk-through's length, s, from bring-up to the loop's stop: its "
                        "pauses stretch to end it then (default 16; steps slower than their "
                        "share make it longer; set-up and the plot come on top)")
    p.add_argument("--record", default=None, metavar="DIR",
                   help="where the recording and its plot go (default: a new directory "
                        "under ~/.local/state/rocoma-can/demo/)")
    p.add_argument("--no-record", action="store_true", help="no recording, no plot")
    p.add_argument("--flight-dir", default=None, metavar="DIR",
                   help="where each e-stop's flight record goes, as with run (default: "
                        "flight/ in the recording's directory, or run's default without one)")
    p.add_argument("--no-flight", action="store_true", help="no flight recorder")
    p.add_argument("--priority", type=rt_priority, default=None, metavar="1..99",
                   help="run the loop's thread SCHED_FIFO at this priority, as a robot's "
                        "realtime.priority (needs CAP_SYS_NICE or an rtprio limit; refused: "
                        "said, and the demo runs at normal priority). Default: normal")
    from .commands import add_foxglove_options
    add_foxglove_options(p)
    from ..ros2.config import add_ros2_options
    add_ros2_options(p, connect=True)
    p.add_argument("--zenoh-listen", default=None, metavar="ENDPOINT",
                   help="serve the demo's manager on Zenoh as rocoma/demo at ENDPOINT "
                        "(e.g. tcp/127.0.0.1:7447): watch and e-stop it from another shell")
    p.set_defaults(func=_main)


def _main(args: argparse.Namespace) -> int:
    buses = default_buses(args.drives) if args.buses is None else args.buses
    if not 2 <= args.drives <= 32 or not 10 <= args.rate <= 2000 or not args.duration > 0 \
            or not 1 <= buses <= args.drives // 2:
        print("demo: --drives 2..32, --rate 10..2000 Hz, --duration > 0, --buses 1.."
              "drives/2 (the walk-through faults two drives of the first bus)", flush=True)
        return USAGE
    if args.data_bitrate is not None and (not args.fd or not FD_BITRATE <= args.data_bitrate
                                          <= MAX_DATA_BITRATE):
        print(f"demo: --data-bitrate: the data phase of --fd buses, {FD_BITRATE}.."
              f"{MAX_DATA_BITRATE} bit/s, got {args.data_bitrate}"
              + ("" if args.fd else " without --fd"), flush=True)
        return USAGE
    try:
        check_choice(args.sim, args.interface)
    except ValueError as exc:
        print(f"demo: {exc}", flush=True)
        return USAGE
    data_bitrate = (args.data_bitrate or FD_DATA_BITRATE) if args.fd else None
    from .commands import default_flight_dir, foxglove_from_args
    try:
        foxglove = foxglove_from_args(args)
    except ValueError as exc:
        print(f"demo: {exc}", flush=True)
        return USAGE
    from ..ros2.config import from_args as ros2_from_args
    problems: list[str] = []
    ros2 = ros2_from_args(args, None, problems)
    if problems:
        for problem in problems:
            print(f"demo: {problem}", flush=True)
        return USAGE
    record = None if args.no_record else Path(args.record or default_record_dir())
    if record is not None:
        try:
            record.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            print(f"demo: --record {record}: cannot create the directory: {exc}", flush=True)
            return USAGE
    flight = None if args.no_flight else Path(
        args.flight_dir or (record / "flight" if record is not None else default_flight_dir()))
    out = ThreadedLines()
    try:
        report = run_demo(args.drives, args.rate, args.duration,
                          out=out, buses=args.buses,
                          interface=args.interface, eds=args.eds, record=record,
                          zenoh_listen=args.zenoh_listen, flight=flight,
                          foxglove=foxglove, data_bitrate=data_bitrate,
                          sim=args.sim, priority=args.priority, ros2=ros2)
    except SimulatorFailed as exc:  # its drives' process did not start
        print(f"demo: {exc}", flush=True)
        return FAILED
    except RecordingError as exc:  # --record DIR: not writable, or an earlier recording
        print(f"demo: --record: {exc}", flush=True)
        return USAGE
    except (ValueError, RocomaError) as exc:
        if isinstance(exc, ConfigError):  # --zenoh-listen that is no endpoint: "demo: ..."
            for problem in exc.problems:
                print(problem, flush=True)
        elif isinstance(exc, ValueError):  # a file that is no EDS, or one it cannot drive
            print(f"demo: --eds: {exc}", flush=True)
        else:  # Zenoh: not installed, the endpoint taken
            print(f"demo: {exc}", flush=True)
        if record is not None and not any(record.iterdir()):
            record.rmdir()  # it did not run: no empty recording directory left behind
        return USAGE
    hint = path_hint()
    if hint is not None:
        out(hint)
    if out.gone:
        return PIPE_CLOSED
    if report.interrupted:
        return INTERRUPTED
    return OK if report.ok else FAILED


def path_hint() -> str | None:
    """How to get the ``rocoma-can`` command when the shell would not find it.

    ``bash tools/demo`` runs .venv/bin/rocoma-can without activating the venv, and the
    README's next step is ``rocoma-can check-config``: "command not found", unless this
    says how. None when a ``rocoma-can`` is on PATH."""
    if shutil.which("rocoma-can") is not None:
        return None
    activate = Path(sys.prefix) / "bin" / "activate"
    install = f"pip install -e '.[{README_EXTRAS}]' from a checkout"
    if not activate.is_file():
        return f"rocoma-can: not on PATH; for the README's commands: {install}"
    shown = os.path.relpath(activate) if activate.is_relative_to(Path.cwd()) else activate
    return f"rocoma-can: not on PATH; for the README's commands: . {shown} (or {install})"


#: the extras the README's commands need: recording and plots, status --watch, Zenoh, the
#: Foxglove live view (run --foxglove, demo --foxglove)
README_EXTRAS = "record,plot,live,zenoh,foxglove,ros2"
