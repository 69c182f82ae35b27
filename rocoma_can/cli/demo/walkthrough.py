"""The demo's run (``Walkthrough``): the config of its simulated robot, the simulated
drives, the runtime with its manager, the operator's walk-through on a thread of its own
(steps.py) while the loop runs, then the loop's torque-off frames judged (probe.py), the
summary, the flight records and the plot. One method per step, in the order they come;
what the command line chooses is a DemoOptions."""
from __future__ import annotations

import importlib.util
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from ...drivers.protocol.cia301 import SDO_TX
from ...node.client import ManagerClient
from .config import (
    DEFAULT_INTERFACE,
    ESTOP_COB_ID,
    FD_BITRATE,
    MANAGER_ID,
    ZENOH_PREFIX,
    Emulated,
    default_buses,
    demo_config,
    demo_urdf,
    emulate,
)
from .drives import DemoSimulator, InProcessSim, SimProcess, check_choice
from .probe import TorqueOffProbes
from .report import DemoReport, Said, Step, note_lines, recording_stopped, status_ticker, summary
from .steps import DemoOperator, StateWatch
from .stops import OutsideStop

#: the demo's flight recorder window, s: run keeps 10, but e-stops within half a window make
#: one record, and the walk-through's come seconds apart
FLIGHT_SECONDS = 2.0

if TYPE_CHECKING:  # imported by Walkthrough.run(): `rocoma-can --help` must not import them
    from ...live.foxglove import FoxgloveConfig
    from ...ros2.config import Ros2Config
    from ...runtime.config import RuntimeConfig
    from ...runtime.loop import TimingSummary
    from ...runtime.system import Runtime


@dataclass
class DemoOptions:
    """What the walk-through runs on. ``eds``: the simulated drives emulate this EDS/DCF
    and the demo uses the modes it supports, skipping (with the reason) the steps it cannot
    do; ``record``: a directory for the run's recording (``run --record``'s files) and its
    plot ``demo.png``; ``zenoh_listen``: an endpoint the manager serves Zenoh on, under the
    prefix ``rocoma/demo`` (another shell can watch and e-stop it); ``duration``: s from the
    start of bring-up to the loop's stop (steps.py's pace); ``flight``: the flight
    recorder's directory, as ``run`` has it: each e-stop leaves a record there, its path
    said as it is written. Its window is FLIGHT_SECONDS, not run's 10 s: e-stops within
    half a window make one record, and the walk-through's are seconds apart. ``foxglove``:
    the live view, as ``run --foxglove`` serves it. ``data_bitrate``: the buses are CAN FD
    buses (config.py's FD_BITRATE and this data bit rate): every frame an FD frame with bit
    rate switching, the drives' PDOs up to FD_PDO_BYTES, the load checked as for real buses
    (ConfigError when it does not fit). ``channel``: the in-process channel (several buses:
    ``channel-0``, ...) another part of this process can listen on; default: a new one per
    run. ``sim``: where the simulated drives run, ``loop`` (stepped by the loop's thread
    after each write) or ``process`` (one of their own; drives.py). ``priority``: the
    loop's thread runs SCHED_FIFO at it, as a robot's ``realtime.priority`` has it; where
    the system refuses, the summary says why and the demo runs on at normal priority.
    ``ros2``: the manager as a ROS 2 node, as ``run --ros2`` serves it."""
    drives: int = 6
    rate: float = 200.0
    duration: float = 16.0
    buses: int | None = None
    interface: str = DEFAULT_INTERFACE
    eds: str | None = None
    record: str | Path | None = None
    zenoh_listen: str | None = None
    flight: str | Path | None = None
    foxglove: FoxgloveConfig | None = None
    data_bitrate: int | None = None
    channel: str | None = None
    sim: str = "loop"
    priority: int | None = None
    ros2: Ros2Config | None = None


def _only(cob_ids: set[int]) -> list[can.typechecking.CanFilter]:
    """Filters that pass these 11-bit COB-IDs only."""
    return [{"can_id": c, "can_mask": 0x7FF, "extended": False} for c in sorted(cob_ids)]


class Walkthrough:
    """``rocoma-can demo``'s run: ``run()`` takes each step in order and returns the report
    (its steps, latencies, recording and plot); ``out`` says each line."""

    def __init__(self, options: DemoOptions, out: Callable[[str], None] = print) -> None:
        self.options = options
        self.out = out
        self.report = DemoReport()
        self.buses = default_buses(options.drives) if options.buses is None else options.buses
        self.channel = options.channel or f"rocoma-demo-{uuid.uuid4().hex[:8]}"
        self.fd = options.data_bitrate is not None
        self.record, self.flight = options.record, options.flight
        self.watch = StateWatch()
        self.stop = threading.Event()
        self.simulator: DemoSimulator | None = None

    def run(self) -> DemoReport:
        emulated = self.emulate()
        config = self.configure(emulated)
        notes = self.say_plan(config)
        self.check_recorder()
        said = Said(set(notes))  # the hardware logs each drive's notes: said above, grouped
        hardware_log = logging.getLogger("rocoma_can.drivers.hardware")
        hardware_log.addFilter(said)
        try:
            with self.parts(config, emulated) as (probes, client_bus):
                rt = self.run_loop(config, probes, client_bus)
                self.finish(rt)
        finally:
            hardware_log.removeFilter(said)
        return self.report

    def emulate(self) -> Emulated | None:
        """The drives fitted to ``--eds``'s file (None: the demo's own drives)."""
        eds = self.options.eds
        emulated = emulate(eds, self.options.drives) if eds else None
        if emulated is not None:
            self.out(f"rocoma-can demo: the drives emulate {eds}: modes "
                     f"{', '.join(emulated.modes)}")
            for note in emulated.notes:
                self.out(f"  note: {note}")
        return emulated

    def configure(self, emulated: Emulated | None) -> RuntimeConfig:
        """The demo's robot as a config, checked as any config is."""
        from ...live.urdf import parse_urdf
        from ...runtime.config import validate
        o = self.options
        raw = demo_config(self.channel, o.drives, o.rate, self.buses, o.interface, emulated,
                          o.data_bitrate, o.priority)
        if o.zenoh_listen is not None:
            raw["zenoh"] = {"prefix": ZENOH_PREFIX, "listen": [o.zenoh_listen],
                            "multicast": False}
        config = validate(raw, source="demo")
        config.ros2 = o.ros2
        config.robot = parse_urdf(demo_urdf([d.name for d in config.drives]).encode(), "demo")
        return config

    def say_plan(self, config: RuntimeConfig) -> dict[str, str]:
        """The drives' notes, each once, and the buses' load; the notes said."""
        notes = note_lines(config.plans)
        for line in notes.values():
            self.out(line)
        said_load = _load_line(config)
        if said_load is not None:
            self.out(said_load)
        return notes

    def check_recorder(self) -> None:
        """No recording and no flight records without the MCAP writer (said)."""
        if (self.record is not None or self.flight is not None) \
                and importlib.util.find_spec("mcap") is None:
            self.out("rocoma-can demo: not recording, no flight records: MCAP needs pip "
                     "install 'rocoma-can[record]'")
            self.record = self.flight = None

    @contextmanager
    def parts(self, config: RuntimeConfig, emulated: Emulated | None
              ) -> Iterator[tuple[TorqueOffProbes, can.BusABC]]:
        """The simulated drives, the torque-off probes and the operator's bus, closed after."""
        from ...drivers.link.bus import open_bus
        o = self.options
        sim_buses = [(b.channel, [d.node_id for d in config.drives_on(b)])
                     for b in config.buses]
        as_fd: dict[str, Any] = {"fd": True} if self.fd else {}  # SocketCAN: FD frames to
        probes = TorqueOffProbes(config, lambda bus, cob_ids: open_bus(  # FD sockets
            o.interface, bus, receive_own_messages=False, can_filters=_only(cob_ids),
            **as_fd))
        client_bus: can.BusABC | None = None
        try:
            # the drives stepped by the loop, or in a process of their own (drives.py: as a
            # robot's compute in theirs; python-can's virtual bus joins no other process)
            check_choice(o.sim, o.interface)
            if o.sim == "loop":
                self.simulator = InProcessSim(sim_buses, o.interface, emulated, self.fd)
            else:
                self.simulator = SimProcess(sim_buses, o.eds, o.drives, self.fd)
            # The client and the probes (probe.py: from the walk-through's end) filter what
            # they read (the interface drops the rest): at 1 kHz every bus carries ~13
            # frames a cycle, and readers of all of it cost the loop's process more CPU than
            # the drives' simulation.
            client_bus = open_bus(o.interface, config.node_bus.channel,
                                  receive_own_messages=False,
                                  can_filters=_only({SDO_TX + MANAGER_ID}), **as_fd)
            yield probes, client_bus
        finally:
            probes.close()
            if client_bus is not None:
                client_bus.shutdown()
            if self.simulator is not None:
                self.simulator.stop()

    def run_loop(self, config: RuntimeConfig, probes: TorqueOffProbes,
                 client_bus: can.BusABC) -> Runtime:
        """The runtime, the walk-through beside its loop, then the loop's stop judged and
        the summary; the runtime, closed."""
        from ...runtime.system import Runtime
        assert self.simulator is not None
        on_cycle = (self.simulator.on_cycle(self.watch)
                    if isinstance(self.simulator, InProcessSim) else self.watch)
        o = self.options
        with Runtime(config, on_cycle=on_cycle,
                     record=None if self.record is None else str(self.record),
                     flight=None if self.flight is None else str(self.flight),
                     flight_seconds=FLIGHT_SECONDS, foxglove=o.foxglove,
                     announce=lambda text: self.out(f"rocoma-can demo: {text}")) \
                as rt, ManagerClient(client_bus, MANAGER_ID) as client:
            self.watch.runtime = rt
            self.announce(rt, config)
            timing = self.walk(rt, client, probes)
            time.sleep(0.1)  # the probes run on their buses' reader threads
            self.judge(rt, probes, timing)
        return rt

    def announce(self, rt: Runtime, config: RuntimeConfig) -> None:
        """What runs where, and how to reach it from another shell."""
        o, out = self.options, self.out
        assert self.simulator is not None
        kind = f"{o.interface} CAN FD" if self.fd else o.interface
        on = (f"{kind} bus {config.bus.channel}" if self.buses == 1
              else f"{self.buses} {kind} buses {self.channel}-0..{self.buses - 1}")
        out(f"rocoma-can demo: {o.drives} simulated drives, {o.rate:g} Hz, manager node "
            f"{MANAGER_ID}, e-stop COB-ID 0x{ESTOP_COB_ID:03X} ({on})")
        out(f"rocoma-can demo: the simulated drives run {self.simulator.where}")
        if rt.foxglove is not None:
            from ...live.foxglove import describe_view
            out(f"rocoma-can demo: {describe_view(rt.foxglove)}")
        if rt.ros2 is not None:
            from ...ros2.node import describe_node
            out(f"rocoma-can demo: {describe_node(rt.ros2)}")
        if o.zenoh_listen is not None:
            out(f"rocoma-can demo: on Zenoh as {ZENOH_PREFIX} at {o.zenoh_listen}; from "
                f"another shell: rocoma-can status --watch --zenoh {ZENOH_PREFIX} "
                f"--zenoh-connect {o.zenoh_listen} --zenoh-no-multicast (estop: the same "
                "with estop)")

    def walk(self, rt: Runtime, client: ManagerClient, probes: TorqueOffProbes
             ) -> TimingSummary:
        """The loop runs; the operator walks through its steps and a status line comes each
        second meanwhile, on threads of their own. An operator's e-stop ends the walk."""
        assert self.simulator is not None
        outside = OutsideStop(self.stop)
        rt.manager.subscribe(outside)  # (the manager goes with the runtime)
        operator = DemoOperator(rt, self.simulator, client, self.watch, probes, self.report,
                                self.options.duration, self.stop, outside, self.out)
        walking = threading.Thread(target=operator.walk, name="demo-operator")
        status = threading.Thread(target=status_ticker, name="demo-status",
                                  args=(rt, self.stop, self.out))
        walking.start()
        status.start()
        try:
            return rt.run(duration=self.options.duration * 3 + 20)
        finally:
            self.stop.set()
            walking.join(15.0)
            status.join(2.0)

    def judge(self, rt: Runtime, probes: TorqueOffProbes, timing: TimingSummary) -> None:
        """The loop's stop seen as torque-off frames, the recording's health, the summary."""
        step = Step("loop stop -> torque-off frames", *probes.judge(
            rt.loop.stop_reason, int(rt.loop.last_state), self.options.drives,
            bool(self.report.interrupted)))
        self.report.steps.append(step)
        self.out(step.line())
        if rt.recording is not None and rt.recording.errors:  # (a full disk, the writer
            recording_stopped(self.report, rt.recording.errors)  # killed)
            self.out(f"FAILED recording: {rt.recording.errors[0]}")
        summary(self.out, self.report, timing, rt)

    def finish(self, rt: Runtime) -> None:
        """After the runtime closed, before the drives stop: its flight records (the last
        one written), the simulated drives' health, the plot of the recording."""
        from .report import plot_run
        if rt.flight is not None:
            self.report.flight_records = list(rt.flight.dumps)
            self.out(f"flight records: {len(self.report.flight_records)} in "
                     f"{rt.flight.directory}")
        assert self.simulator is not None
        try:
            self.simulator.check()
        except RuntimeError as exc:  # a drive's bug, or the drives' process died
            self.report.steps.append(Step("simulated drives", False, str(exc)))
            self.out(f"FAILED simulated drives: {exc}")
        if self.record is not None:
            plot_run(Path(self.record), self.report, self.out,
                     rt.recording.errors if rt.recording is not None else ())


def _load_line(config: RuntimeConfig) -> str | None:
    """What the buses carry as the buses they stand for: the load of CAN FD ones (--fd:
    checked, as for real buses), or, where in-process buses without a bit rate carry what
    a real classic 1 Mbit/s bus would not, a note that says so (and what fits)."""
    if config.loads:
        busiest = max(config.loads.values(), key=lambda planned: planned.load)
        return (f"rocoma-can demo: the busiest bus: {busiest.explain()} "
                f"({busiest.frames_per_cycle} frames a cycle)")
    from ...runtime.bus_load import bus_load
    for b in config.buses:
        classic = bus_load([config.plans[d.name].layout for d in config.drives_on(b)],
                           config.rate, FD_BITRATE)
        if classic.load > 1.0:
            return (f"  note: 1 Mbit/s classic buses would not carry this ({b.label}: "
                    f"{classic.explain()}); the in-process ones do (--fd: CAN FD buses, "
                    "checked as real ones)")
    return None


