"""The demo's operator: the walk-through's steps, one method each, talking to the manager
only the way another CAN node would (SDO and a raw e-stop frame): bring-up, clear and
switch to pd, switch to trajectory (bumpless, by swap state), a drive fault -> emergency
controller (damp), a second fault -> failproof torque-off, recovery of the drives, a
switch back to pd, an e-stop by a raw CAN frame. Each step checks what it should and says
its verdict; the loop's watch (StateWatch) gives the latency of each reaction. An
operator's e-stop from outside (stops.py) or the loop's stop ends the walk early."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import can

from ...events import ManagerState
from ...node.client import ManagerClient
from ...node.objects import CLEAR, ESTOP_CAUSE, RECOVER, STATE_NAMES, SWITCH_NAME, SWITCH_REFUSAL
from .config import ESTOP_COB_ID, MIN_PAUSE, PAUSES
from .drives import DemoSimulator
from .probe import TorqueOffProbes
from .report import DemoReport, Step
from .stops import Ended, LoopStopped, OutsideStop, loop_running

if TYPE_CHECKING:
    from ...runtime.system import Runtime


class StateWatch:
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


class DemoOperator:
    """The walk-through's steps (``walk``, on a thread of its own while the loop runs)."""

    def __init__(self, rt: Runtime, sim: DemoSimulator, client: ManagerClient,
                 watch: StateWatch, probes: TorqueOffProbes, report: DemoReport,
                 duration: float, stop: threading.Event, outside: OutsideStop,
                 say: Callable[[str], None]) -> None:
        self.rt, self.sim, self.client, self.watch = rt, sim, client, watch
        self.probes, self.report, self.stop, self.outside, self.say = \
            probes, report, stop, outside, say
        self.hw, self.mgr = rt.hardware, rt.manager
        self.pace = _Pace(duration, stop)
        self.pauses = iter(PAUSES)
        self.first_faulted = 0  # the node the first fault tripped

    def walk(self) -> None:
        """Every step in order, until one that the rest depend on fails; the walk ends
        early by an operator's e-stop (Ended), the loop's stop (LoopStopped) or an SDO
        failure, each a step of the report. The loop is stopped at the end."""
        try:
            for step in (self.bring_up, self.switch_to_pd, self.switch_to_trajectory,
                         self.first_fault, self.second_fault, self.recover,
                         self.final_switch, self.estop_frame):
                if not step():
                    return
        except Ended as ended:
            self.ended_by_operator(str(ended))
        except LoopStopped as stopped:
            signalled = str(stopped).startswith("signal ")
            if signalled:
                self.report.interrupted = str(stopped)
            self.report.steps.append(Step("walk-through", signalled, f"cut short: the loop "
                                          f"stopped ({stopped}); the steps after it not run"))
            self.say(f"{'stop' if signalled else 'FAILED'} walk-through: "
                     f"{self.report.steps[-1].detail}")
        except Exception as exc:  # an SDO failure is a failed step, and the demo ends
            self.report.steps.append(Step("operator", False,
                                          f"{type(exc).__name__}: {exc}{self._why()}"))
            self.say(f"FAILED operator: {self.report.steps[-1].detail}")
        finally:
            # the probes' buses open: the stop's torque-off frames wait in their queues
            self.probes.arm(self.rt.loop.stop_reason or None)
            self.report.walk_time = time.monotonic() - self.pace.start
            self.rt.loop.stop("walk-through finished")

    # --- the steps, in order: each returns whether the walk goes on --------------------------

    def bring_up(self) -> bool:
        hw = self.hw

        def failed() -> bool:  # a drive that failed start-up ends the wait at once
            return any(d.phase == "FAILED" for d in hw.drive_status())
        _wait(lambda: hw.all_ready or failed(), 30.0, self.stop)
        return self.step("bring-up", hw.all_ready,
                         f"{len(hw.drives_config)} drives configured, mapped and started"
                         if hw.all_ready else hw.not_ready() or "drives not ready")

    def switch_to_pd(self) -> bool:
        self.outside.go_on(self.mgr.estop_requested)  # (before a command that could undo a stop)
        self.client.write(CLEAR, 1)  # must-clear starts latched, like an e-stop button
        result = self.client.switch("pd")
        if not self.step(f"switch to pd (SDO 0x{SWITCH_NAME:04X})",
                         result == 0 and _wait(lambda: self.hw.all_enabled, 3.0, self.stop),
                         f"result {result}, drives enabled: {self.hw.all_enabled}"):
            return False
        self.hold()
        return True

    def switch_to_trajectory(self) -> bool:
        result = self.client.switch("trajectory")
        self.step("switch pd -> trajectory (swap state)", result == 0 and self.state() == 2,
                  f"result {result}, active {self.mgr.active_controller_name}")
        self.hold()
        return True

    def first_fault(self) -> bool:
        ids = self.sim.node_ids
        node = self.first_faulted = ids[min(2, len(ids) - 2)]  # not the last: that one is next
        ok = self.fault(node, "EMERGENCY", 1)
        self.step(f"fault on drive {node} -> emergency controller", ok,
                  f"state {STATE_NAMES[self.state()]}, active {self.mgr.active_controller_name}")
        self.hold()
        return True

    def second_fault(self) -> bool:
        node = self.sim.node_ids[-1]
        if node == self.first_faulted:
            self.step("second fault -> failproof torque-off", True,
                      "skipped: one drive, and it is faulted already")
            self.mgr.failproof_stop("demo: the step the second fault would have shown")
        else:
            ok = self.fault(node, "FAILPROOF", 0)
            self.step(f"second fault on drive {node} -> failproof torque-off", ok,
                      f"state {STATE_NAMES[self.state()]}")
        self.hold()
        return True

    def recover(self) -> bool:
        hw, mgr = self.hw, self.mgr
        self.outside.go_on(mgr.estop_requested)
        self.client.write(RECOVER, 1)  # on success the e-stop latch is cleared
        # done when the switch guard says so: the recovery clears the latch a moment before
        # it reports its own end, and a switch in between is refused ("a recovery is in
        # progress")
        ok = _wait(lambda: hw.not_ready() is None and not mgr.estop_latched, 8.0, self.stop)
        self.step(f"recovery (SDO 0x{RECOVER:04X})", ok,
                  f"drives ready: {hw.all_ready}, latched: {mgr.estop_latched}"
                  + ("" if ok else f"; {hw.not_ready() or 'not ready'}"))
        return True

    def final_switch(self) -> bool:
        result = self.client.switch("pd")
        self.step("final switch to pd", result == 0 and self.state() == 2
                  and _wait(lambda: self.hw.all_enabled, 3.0, self.stop), f"result {result}")
        self.hold()
        return True

    def estop_frame(self) -> bool:
        mark, t0 = len(self.watch.changes), time.monotonic()
        self.client.bus.send(can.Message(arbitration_id=ESTOP_COB_ID, data=b"\x01",
                                         is_extended_id=False))
        ok = self.reached(f"CAN e-stop frame 0x{ESTOP_COB_ID:03X} -> EMERGENCY", t0, mark,
                          {1}, 2.0)
        self.step(f"e-stop by a raw CAN frame on 0x{ESTOP_COB_ID:03X}", ok,
                  f"state {STATE_NAMES[self.state()]}, "
                  f"cause {self.client.read_text(ESTOP_CAUSE)!r}")
        self.hold()
        return True

    # --- what the steps share -----------------------------------------------------------------

    def ended_by_operator(self, cause: str) -> None:
        """An operator's e-stop ended the walk: the robot stays stopped. The stop is heard a
        cycle late (the event thread): a command the walk-through gave meanwhile (clear and
        switch) may have undone it; it is given again."""
        mgr = self.mgr
        if mgr.state is ManagerState.OK or not mgr.estop_latched:
            mgr.emergency_stop(cause=f"demo: {cause}, again (a command of the walk-through "
                                     "came with it)")
        self.report.steps.append(Step("walk-through", True, f"ended early by an e-stop from "
                                      f"outside it ({cause}): the robot stays stopped, the "
                                      f"steps after it not run"))
        self.say(f"ok  walk-through: {self.report.steps[-1].detail}")

    def _why(self) -> str:
        """A refused switch's reason and the state's cause, for a failed step (best effort)."""
        try:
            return (f"; refusal: {self.client.read_text(SWITCH_REFUSAL)!r}; state "
                    f"{STATE_NAMES[self.state()]}, "
                    f"cause {self.client.read_text(ESTOP_CAUSE)!r}")
        except Exception:  # noqa: BLE001 - the report is best effort
            return ""

    def hold(self) -> None:
        self.pace.pause(next(self.pauses))
        loop_running(self.rt.loop.stop_reason)
        self.outside.go_on()

    def step(self, name: str, ok: bool, detail: str = "") -> bool:
        loop_running(self.rt.loop.stop_reason)  # a step the loop's stop cut short is not judged
        self.outside.go_on()  # nor one an operator's stop cut short
        self.report.steps.append(Step(name, ok, detail))
        self.say(self.report.steps[-1].line())
        return ok

    def state(self) -> int:
        return int(self.mgr.state)

    def fault(self, node: int, becomes: str, target: int) -> bool:
        """Trip a drive's fault; whether the manager reached ``target`` in time."""
        mark = len(self.watch.changes)
        t0 = self.sim.trip_fault(node)
        return self.reached(f"drive {node} fault -> {becomes}", t0, mark, {target}, 2.0)

    def reached(self, what: str, t0: float, mark: int, to: set[int], timeout: float) -> bool:
        """Whether the loop's state went into ``to`` after the event (within ``timeout``),
        as the loop's watch recorded it, and then its latency. Judged by the watch, not by
        the manager's state: the watch runs after the cycle's write and the simulator's
        step, so on a loaded host the manager's state could already show the change the
        watch had not yet recorded, and the latency went missing."""
        hit: tuple[float, int] | None = None

        def seen() -> bool:
            nonlocal hit
            hit = self.watch.first_change_since(mark, to)
            return hit is not None

        if not _wait(seen, timeout, self.stop) or hit is None:
            return False
        took = max(0.0, hit[0] - t0)  # the reacting cycle may have begun just before
        self.report.latencies.append((what, took, max(1, round(took / self.rt.config.dt))))
        return True
