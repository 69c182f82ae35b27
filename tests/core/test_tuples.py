"""rocoma_can/tuples.py: ControllerTuple: order, stop-at-first-failure, shared objects, swap-state
slots."""
from __future__ import annotations

import logging

import pytest

from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.interfaces import Controller, EmergencyController, SwapState
from rocoma_can.tuples import ControllerTuple, EmergencyControllerTuple, TupleSwapState
from rocoma_can.workers import WorkerManager, WorkerOptions


class Pose(SwapState):
    def __init__(self, owner: str) -> None:
        self.owner = owner


class Member(Controller):
    """Logs every call into a shared list; ``fail`` calls return False, ``boom`` calls raise."""

    def __init__(self, name: str, log: list, fail: set[str] = frozenset(),
                 boom: set[str] = frozenset()) -> None:
        super().__init__(name)
        self.log = log
        self.fail = set(fail)
        self.boom = set(boom)
        self.swapped_with: list[object] = []

    def _record(self, call: str) -> bool:
        self.log.append((self.name, call))
        if call in self.boom:
            raise RuntimeError(f"{self.name}.{call} exploded")
        return call not in self.fail

    def create(self, dt): return self._record("create")
    def initialize(self, dt): return self._record("initialize")
    def reset(self, dt): return self._record("reset")
    def advance(self, dt): return self._record("advance")
    def pre_stop(self): return self._record("pre_stop")
    def stop(self): return self._record("stop")
    def cleanup(self): return self._record("cleanup")

    def swap(self, dt, swap_state):
        self.swapped_with.append(swap_state)
        return super().swap(dt, swap_state)  # reset if initialized, else initialize

    def get_swap_state(self):
        return Pose(self.name)


class Brake(Member, EmergencyController):
    def initialize_fast(self, dt): return self._record("initialize_fast")


def make(n: int = 3, cls=Member, tuple_cls=ControllerTuple, **faults):
    log: list = []
    members = [cls(f"m{i}", log, **faults.get(f"m{i}", {})) for i in range(n)]
    return tuple_cls("combo", members), members, log


@pytest.mark.parametrize("call, args", [
    ("create", (0.01,)), ("initialize", (0.01,)), ("reset", (0.01,)), ("advance", (0.01,)),
    ("pre_stop", ()), ("stop", ()), ("cleanup", ()),
])
def test_calls_are_forwarded_in_order(call, args):
    combo, _, log = make()
    assert getattr(combo, call)(*args) is True
    assert log == [("m0", call), ("m1", call), ("m2", call)]


def test_advance_stops_at_the_first_failure():
    combo, _, log = make(m1=dict(fail={"advance"}))
    assert combo.advance(0.01) is False
    assert log == [("m0", "advance"), ("m1", "advance")]
    assert combo.failed_member == "m1"


def test_advance_exception_propagates_to_the_adapter():
    combo, _, log = make(m0=dict(boom={"advance"}))
    with pytest.raises(RuntimeError, match="m0.advance exploded"):
        combo.advance(0.01)
    assert log == [("m0", "advance")]


def test_initialize_stops_at_the_first_failure_and_tracks_member_flags(caplog):
    combo, members, log = make(m1=dict(fail={"initialize"}))
    assert combo.initialize(0.01) is False
    assert log == [("m0", "initialize"), ("m1", "initialize")]
    assert [m.is_initialized for m in members] == [True, False, False]
    assert any("initialize of member 'm1' failed" in r.getMessage() for r in caplog.records)


def test_stop_reaches_every_member_even_after_a_failure(caplog):
    combo, members, log = make(m0=dict(boom={"stop"}), m1=dict(fail={"stop"}))
    assert combo.initialize(0.01)
    log.clear()
    with caplog.at_level(logging.ERROR, logger="rocoma_can.tuples"):
        assert combo.stop() is False
    assert log == [("m0", "stop"), ("m1", "stop"), ("m2", "stop")]
    assert not any(m.is_initialized for m in members)
    raised = [r for r in caplog.records if r.exc_info]
    assert len(raised) == 1 and "stop of member 'm0' raised" in raised[0].getMessage()


@pytest.mark.parametrize("call", ["pre_stop", "cleanup"])
def test_pre_stop_and_cleanup_reach_every_member(call):
    combo, _, log = make(m0=dict(fail={call}), m1=dict(boom={call}))
    assert getattr(combo, call)() is False
    assert log == [("m0", call), ("m1", call), ("m2", call)]


def test_shared_objects_reach_members_and_names_stay_their_own():
    combo, members, _ = make(2)
    inner = ControllerTuple("inner", [Member("deep", [])])
    outer = ControllerTuple("outer", [combo, inner])
    state, command, workers = JointState.zeros(2), JointCommand.zeros(2), WorkerManager("outer")
    outer.dt, outer.state, outer.command, outer.workers = 0.002, state, command, workers
    for c in [combo, *members, inner, inner.controllers[0]]:
        assert c.dt == 0.002 and c.state is state and c.command is command
        assert c.workers is workers
    assert [m.name for m in members] == ["m0", "m1"] and outer.name == "outer"
    assert outer.controllers == (combo, inner)


def test_members_register_workers_with_the_tuple_manager():
    combo, members, _ = make(2)
    combo.workers = WorkerManager("combo")
    calls = []
    handle = members[1].add_worker(WorkerOptions("tick", lambda e: calls.append(e) or False,
                                                 frequency=100.0, autostart=True))
    assert handle.thread_name == "combo/tick"
    assert combo.workers.cancel_all(timeout=5.0)
    assert combo.workers.active_workers == []


def test_get_swap_state_has_one_slot_per_member():
    combo, _, _ = make()
    state = combo.get_swap_state()
    assert isinstance(state, TupleSwapState) and len(state) == 3
    assert [s.owner for s in state.states] == ["m0", "m1", "m2"]
    assert state.find(Pose).owner == "m0"
    assert state.find(TupleSwapState) is None


def test_swap_from_a_same_shaped_tuple_goes_by_position():
    source, _, _ = make()
    combo, members, log = make()
    assert combo.swap(0.01, source.get_swap_state())
    assert [m.swapped_with[0].owner for m in members] == ["m0", "m1", "m2"]
    # Not initialized yet: the members' default swap initializes them.
    assert log == [("m0", "initialize"), ("m1", "initialize"), ("m2", "initialize")]
    log.clear()
    assert combo.swap(0.01, source.get_swap_state())
    assert log == [("m0", "reset"), ("m1", "reset"), ("m2", "reset")]


def test_swap_with_any_other_state_gives_every_member_the_whole_state():
    combo, members, _ = make()
    single = Pose("single")
    assert combo.swap(0.01, single)
    assert all(m.swapped_with == [single] for m in members)
    pair = TupleSwapState([Pose("a"), None])
    assert combo.swap(0.01, pair)
    assert all(m.swapped_with[-1] is pair for m in members)
    assert combo.swap(0.01, None)
    assert all(m.swapped_with[-1] is None for m in members)


def test_swap_stops_at_the_first_failure():
    combo, members, log = make(m0=dict(fail={"initialize"}))
    assert combo.swap(0.01, None) is False
    assert log == [("m0", "initialize")]
    assert members[1].swapped_with == []


@pytest.mark.parametrize("members, error, match", [
    ([], ValueError, "at least one member"),
    ([TorqueOff()], TypeError, "member 0 .* not an instance of Controller"),
    ([Member("a", []), "b"], TypeError, "member 1"),
    ([Member("a", []), Member("a", [])], ValueError, "two members named 'a'"),
])
def test_bad_members(members, error, match):
    with pytest.raises(error, match=match):
        ControllerTuple("bad", members)


def test_emergency_tuple():
    combo, members, log = make(tuple_cls=EmergencyControllerTuple, cls=Brake,
                               m1=dict(fail={"initialize_fast"}))
    assert isinstance(combo, EmergencyController)
    assert combo.initialize_fast(0.01) is False
    assert log == [("m0", "initialize_fast"), ("m1", "initialize_fast")]
    assert combo.failed_member == "m1"
    assert [m.is_initialized for m in members] == [True, False, False]
    with pytest.raises(TypeError, match="member 1 .* not an instance of EmergencyController"):
        EmergencyControllerTuple("mixed", [Brake("b", []), Member("m", [])])


def test_a_tuple_with_emergency_members_is_a_plain_controller():
    mixed = ControllerTuple("mixed", [Brake("b", []), Member("m", [])])
    assert not isinstance(mixed, EmergencyController)
