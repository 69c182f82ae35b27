"""rocoma_can/manager.py, switcher.py, stopper.py: random interleavings of update, switch, e-stop,
failproof stop, clear and misbehaving controllers (hypothesis state machine). Invariants: exactly
one layer commands each cycle, and it is the one the manager says; a stopped or uninitialized
controller is never advanced; no thread is left after shutdown."""
from __future__ import annotations

import threading

from fixtures.manager_probes import WAIT, CommandLog, EmergencyProbe, FailproofProbe, Journal, Probe
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from rocoma_can import ControllerManager, ManagerState, SwitchResult

NAMES = ("a", "b", "c")
EMERGENCIES = {"a": "e1", "b": "e1", "c": "e2"}


class Live:
    """Mixin: flags advance calls on a controller that is not initialized or is stopped."""

    def _init_live(self) -> None:
        self.live = False
        self.violations: list[str] = []

    def _mark(self, method: str, ok: bool) -> bool:
        if method in ("initialize", "initialize_fast", "reset") and ok:
            self.live = True
        if method == "stop":
            self.live = False
        return ok

    def advance(self, dt):
        if not (self.live and self.is_initialized):
            self.violations.append(f"{self.name}.advance while not live")
        return super().advance(dt)


class LiveProbe(Live, Probe):
    def __init__(self, name, journal, **kw):
        super().__init__(name, journal, **kw)
        self._init_live()

    def _do(self, method):
        if method == "stop":
            self._mark("stop", True)
        return self._mark(method, super()._do(method))


class LiveEmergencyProbe(LiveProbe, EmergencyProbe):
    pass


class ManagerMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.journal = Journal(update_thread=threading.get_ident())
        self.command = CommandLog()
        self.must_clear = False
        self.mgr = ControllerManager(FailproofProbe("failproof", self.journal), dt=0.001,
                                     command=self.command, timing=None)
        self.journal.manager = self.mgr
        emergencies = {n: LiveEmergencyProbe(n, self.journal) for n in set(EMERGENCIES.values())}
        # Stops are slow by default so that switches and e-stops meet stops in progress.
        self.controllers = {n: LiveProbe(n, self.journal, delay={"stop": 0.005}) for n in NAMES}
        for n, c in self.controllers.items():
            assert self.mgr.add_controller(c, emergency=emergencies[EMERGENCIES[n]])
        self.all = {**self.controllers, **emergencies}
        self.futures = []

    @rule()
    def update(self) -> None:
        self.command.clear()
        state = self.mgr.update()
        assert len(self.command) == 1, f"{len(self.command)} layers commanded: {self.command}"
        writer = self.command[0]
        if state is ManagerState.FAILPROOF:
            assert writer == "failproof"
        elif state is ManagerState.OK:
            assert writer in NAMES
        else:
            assert writer in EMERGENCIES.values()

    @rule(name=st.sampled_from(NAMES + ("nope", "e1", "failproof")))
    def switch(self, name) -> None:
        self.futures.append((name, self.mgr.request_switch(name)))

    @rule(name=st.sampled_from(NAMES))
    def switch_and_wait(self, name) -> None:
        self.mgr.request_switch(name).result(WAIT)

    @rule()
    def emergency_stop(self) -> None:
        self.mgr.emergency_stop("test")

    @rule()
    def failproof_stop(self) -> None:
        self.mgr.failproof_stop("test")

    @rule()
    def clear(self) -> None:
        self.mgr.clear_emergency_stop()

    @rule(name=st.sampled_from(tuple(NAMES) + ("e1", "e2")),
          behaviour=st.sampled_from(["fail", "raise", "ok"]),
          method=st.sampled_from(["advance", "initialize", "initialize_fast", "pre_stop"]))
    def misbehave(self, name, behaviour, method) -> None:
        c = self.all[name]
        c.fail.discard(method)
        c.raises.discard(method)
        if behaviour == "fail":
            c.fail.add(method)
        elif behaviour == "raise":
            c.raises.add(method)

    @rule(name=st.sampled_from(tuple(NAMES) + ("e1", "e2")),
          method=st.sampled_from(["initialize", "stop", "pre_stop"]), slow=st.booleans())
    def slow(self, name, method, slow) -> None:
        if slow:
            self.all[name].delay[method] = 0.01
        else:
            self.all[name].delay.pop(method, None)

    @precondition(lambda self: self.futures)
    @rule()
    def wait_for_switches(self) -> None:
        for name, future in self.futures:
            result = future.result(WAIT)
            if name not in NAMES:
                assert result is SwitchResult.NOT_FOUND
        self.futures.clear()

    @invariant()
    def never_advanced_when_not_live(self) -> None:
        for c in self.all.values():
            assert not c.violations, c.violations

    def teardown(self) -> None:
        for _, future in self.futures:
            future.result(WAIT)
        assert self.mgr.shutdown()
        left = [t.name for t in threading.enumerate() if t.name.startswith("rocoma/")]
        assert not left, left
        self.never_advanced_when_not_live()


TestManagerMachine = ManagerMachine.TestCase
TestManagerMachine.settings = settings(max_examples=100, stateful_step_count=50, deadline=None,
                                       suppress_health_check=[HealthCheck.too_slow])
