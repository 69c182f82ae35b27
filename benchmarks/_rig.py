"""The test rig the loop benchmarks share: simulated CiA 402 drives, the CAN hardware layer,
a manager, the manager's CANopen node and the project's own ControlLoop (rocoma_can.runtime).

Wired the way ``rocoma_can.runtime.Runtime`` wires it, but with controllers given in code,
so a benchmark can add ones that fail or initialize slowly on purpose. The simulator runs
in this process over an in-process bus (default ``inproc``, drivers/link/inproc.py), stepped on
the loop's thread after each write (SegmentGroup.lockstep_pass, as ``rocoma-can demo`` runs
it; ``sim_thread=True``: on a receive thread of its own; ``interface="virtual"``, python-can's
bus, which copies every frame once per receiver, always has a thread per bus), or as
a separate ``rocoma-can sim`` process over SocketCAN vcan0 (``separate_process=True``; needs
vcan, i.e. run the benchmark under tools/vcan-run). ``fd=True``: CAN FD buses, the drives
mapping PDOs of up to 64 bytes (one RPDO and one TPDO a cycle), as ``rocoma-can demo --fd``.
"""
from __future__ import annotations

import math
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from typing import Any

import can
import numpy as np

from rocoma_can.cli.demo.config import FD_PDO_BYTES
from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.link.bus import open_bus
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.sim.group import SegmentGroup
from rocoma_can.drivers.sim.segment import SimulatedSegment
from rocoma_can.interfaces import Controller, EmergencyController
from rocoma_can.node.server import ManagerNode
from rocoma_can.runtime import ControlLoop
from rocoma_can.runtime.system import manager_for

MANAGER_NODE_ID = 100
ESTOP_COB_ID = 0x010
#: The simulated drive's EDS defaults (0x608F, 0x6076): the hardware checks them at start-up.
INCREMENTS_PER_REV = 1 << 20
RATED_TORQUE_NM = 1.0


def drive_configs(n: int, buses: int = 1, pdo_bytes: int = 8) -> list[DriveConfig]:
    """n drives spread over ``buses`` buses named bus0, bus1, ... (node ids from 1 on each)."""
    per_bus = -(-n // buses)
    return [DriveConfig(f"j{i + 1}", i % per_bus + 1, INCREMENTS_PER_REV, RATED_TORQUE_NM,
                        bus=f"bus{i // per_bus}" if buses > 1 else "", pdo_bytes=pdo_bytes)
            for i in range(n)]


def missed_cycles(starts: np.ndarray, period: float) -> int:
    """Cycle slots that passed without a cycle starting: a gap of k periods misses k - 1."""
    if len(starts) < 2:
        return 0
    slots = np.rint(np.diff(starts) / period).astype(np.int64)
    return int(np.maximum(slots - 1, 0).sum())


class StartLog:
    """Cycle start times in an array allocated once (ControlLoop's on_cycle gets ``now``)."""

    def __init__(self, capacity: int) -> None:
        self.starts = np.zeros(capacity)
        self.n = 0

    def add(self, now: float) -> None:
        if self.n < len(self.starts):
            self.starts[self.n] = now
            self.n += 1

    def window(self, t0: float = -math.inf, t1: float = math.inf) -> np.ndarray:
        s = self.starts[:self.n]
        return s[(s >= t0) & (s <= t1)]


class Rig:
    """Drives + hardware + manager + node; ``run(duration, on_cycle)`` runs the loop."""

    def __init__(self, drives: int, rate: float, *, separate_process: bool = False,
                 channel: str | None = None, buses: int = 1,
                 interface: str = "inproc", sim_thread: bool = False,
                 fd: bool = False) -> None:
        self.rate = rate
        self.fd = fd
        self.dt = 1.0 / rate
        self.separate_process = separate_process
        self.interface = "socketcan" if separate_process else interface
        if separate_process and buses > 2:
            raise ValueError("--separate-process runs on vcan0 and vcan1: at most 2 buses")
        base = channel or ("vcan" if separate_process else f"bench-{uuid.uuid4().hex[:8]}")
        # one channel per bus: vcan0, vcan1 / bench-xxxx-0, -1, ... (one bus: as given)
        self.channels = ([channel or ("vcan0" if separate_process else base)] if buses == 1
                         else [f"{base}{k}" if separate_process else f"{base}-{k}"
                               for k in range(buses)])
        self.channel = self.channels[0]
        self.configs = drive_configs(drives, buses, pdo_bytes=FD_PDO_BYTES if fd else 8)
        # an FD bus handle: python-can's virtual says so by its protocol
        as_fd: dict[str, Any] = ({} if not fd else {"protocol": can.CanProtocol.CAN_FD}
                                 if self.interface == "virtual" else {"fd": True})
        self.node_ids = sorted({d.node_id for d in self.configs})
        self._closers: list[Callable[[], Any]] = []
        self.group: SegmentGroup | None = None  # the in-process simulator
        try:
            if separate_process:
                self.segments: list[SimulatedSegment | None] = [
                    self._start_simulator(ch) for ch in self.channels]
            else:  # one receive thread for every segment (drivers/sim/group.py)
                self.segments = []
                for ch in self.channels:
                    segment = SimulatedSegment.open(ch, self.interface, self.node_ids, fd=fd)
                    self._closers.append(segment.stop)  # idempotent
                    self.segments.append(segment)
                group = SegmentGroup(self.segments)
                self._closers.append(group.check)  # closers run in reverse: after stop
                self._closers.append(group.stop)
                # stepped on the loop's thread after each write, unless asked otherwise
                group.start(lockstep=not sim_thread)
                self.group = group
            self.segment = self.segments[0]
            self.buses = [open_bus(self.interface, ch, receive_own_messages=False, **as_fd)
                          for ch in self.channels]
            for bus in self.buses:
                self._closers.append(bus.shutdown)
            self.bus = self.buses[0]
            named = ({"bus": self.bus} if buses == 1
                     else {f"bus{k}": b for k, b in enumerate(self.buses)})
            self.hardware = CanopenHardware(named, self.configs, MANAGER_NODE_ID, self.dt,
                                            estop_cob_id=ESTOP_COB_ID)
            self._closers.append(self.hardware.close)
            self.manager = manager_for(self.hardware)
            self._closers.append(self.manager.shutdown)
            self.node_bus = open_bus(self.interface, self.channel,
                                    receive_own_messages=False, **as_fd)
            self._closers.append(self.node_bus.shutdown)
            # as Runtime wires it: e-stop frames are the hardware's, on every bus, in the cycle
            self.node = ManagerNode(self.manager, MANAGER_NODE_ID, self.node_bus,
                                    estop_cob_id=ESTOP_COB_ID,
                                    estop_in_cycle=self.hardware.set_estop_cob_id)
        except BaseException:
            self.close()
            raise

    def _start_simulator(self, channel: str) -> None:
        nodes = f"{self.node_ids[0]}-{self.node_ids[-1]}"
        proc = subprocess.Popen([sys.executable, "-m", "rocoma_can", "sim", "--interface",
                                 "socketcan", "--channel", channel, "--nodes", nodes,
                                 *(["--fd"] if self.fd else [])])

        def stop() -> None:
            proc.terminate()
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5.0)
        self._closers.append(stop)
        time.sleep(1.0)  # let the simulator open its socket and send boot-ups
        if proc.poll() is not None:
            raise RuntimeError(f"rocoma-can sim exited with {proc.returncode} (is {channel} "
                               "up? run under tools/vcan-run)")
        return None

    def add(self, controller: Controller, emergency: EmergencyController | None = None) -> None:
        if not self.manager.add_controller(controller, emergency=emergency):
            raise RuntimeError(f"could not add controller {controller.name!r}")

    def start(self) -> None:
        self.hardware.start()
        self.node.start()
        self._closers.append(self.node.close)

    def loop(self, on_cycle: Callable[[float], None], cycles: int,
             spin: float | None = None) -> ControlLoop:
        if self.group is not None and self.group.lockstep:
            on_cycle = self.group.stepped_before(on_cycle)  # answers before the loop sleeps
        return ControlLoop(self.hardware, self.manager, self.rate, on_cycle=on_cycle,
                           stats_size=max(16, cycles), spin=spin)

    def close(self) -> None:
        """Everything opened, in reverse order; a failing step does not skip the rest."""
        errors = []
        while self._closers:
            try:
                self._closers.pop()()
            except Exception as exc:  # noqa: BLE001 - close the rest, report the first
                errors.append(exc)
        if errors:
            raise errors[0]

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Script:
    """A scenario stepped from the loop's on_cycle: bring-up, switch, then the benchmark.

    Phases: wait until every drive is READY, switch to ``controller`` and wait until every
    drive is enabled, then call ``body(now)`` every cycle until it returns True (done) or
    ``timeout`` passes (the run is then marked timed out). Stops the loop at the end.
    """

    def __init__(self, rig: Rig, controller: str, body: Callable[[float], bool],
                 timeout: float) -> None:
        self.rig = rig
        self.controller = controller
        self.body = body
        self.timeout = timeout
        self.loop: ControlLoop | None = None
        self.phase = "bring-up"
        self.timed_out = False
        self.ready_at = math.nan
        self._switch: Any = None
        self._deadline = math.inf

    def __call__(self, now: float) -> None:
        if self._deadline == math.inf:
            self._deadline = now + self.timeout
        if now > self._deadline:
            self.timed_out = True
            self.loop.stop(f"timed out in phase {self.phase}")
            return
        hw = self.rig.hardware
        if self.phase == "bring-up":
            if hw.all_ready:
                self._switch = self.rig.manager.request_switch(self.controller)
                self.phase = "enable"
        elif self.phase == "enable":
            if not hw.all_ready and not hw.starting:
                hw.recover()  # a supervision fault during enable (late TPDOs under load)
            elif self._switch.done() and (self.rig.manager.state != 2  # OK
                                          or self.rig.manager.active_controller_name
                                          != self.controller):
                self._switch = self.rig.manager.request_switch(self.controller)  # e-stopped
            if self._switch.done() and hw.all_enabled:
                self.phase = "run"
                self.ready_at = now
        elif self.body(now):
            self.phase = "done"
            self.loop.stop("done")


def run_script(rig: Rig, script: Script, cycles: int,
               start_log: StartLog | None = None, spin: float | None = None) -> Any:
    """Run the loop with ``script`` as on_cycle (and the cycle starts logged); the summary.
    ``spin``: the loop's busy-wait before each deadline (None: its default)."""
    if start_log is None:
        on_cycle = script
    else:
        add = start_log.add

        def on_cycle(now: float) -> None:
            add(now)
            script(now)
    loop = rig.loop(on_cycle, cycles, spin)
    script.loop = loop
    rig.start()
    return loop.run(script.timeout + 5.0)
