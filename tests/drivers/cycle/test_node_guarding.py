"""drivers/cycle/node_guarding.py, drivers/sim/nmt.py: node guarding (CiA 301) for drives that have
no heartbeat (tests/fixtures/eds/guarded.eds: guard time and life time factor, no 0x1016/0x1017, as
Faulhaber's CC and Infranor's Easy-ak files). The cycle sends a remote request to each guarded drive
every ``heartbeat_ms``; the drive answers with its NMT state and a toggle bit, and watches the
requests (life guarding).

Run on python-can's virtual bus (fast suite) and on SocketCAN vcan0 (vcan suite): a remote
frame is a frame of its own kind on a real socket. Every wait is a budget of the setup.
"""
from __future__ import annotations

import math
import struct
import time

import can
import pytest
from fixtures.driver_rig import Rig, seconds_until_all_off, synced_mark
from fixtures.odd_node import Responder, frames
from fixtures.paths import TESTS
from fixtures.rig_controllers import Brake, Sine
from hypothesis import given, settings
from hypothesis import strategies as st

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.bringup.configure import life_time_factor
from rocoma_can.drivers.cycle.node_guarding import NodeGuarding
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_plan import plan_drive
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.joints import JointMode

GUARDED = str(TESTS / "fixtures" / "eds" / "guarded.eds")


@pytest.fixture
def rig_on(can_setup, virtual_channel, sim_segment_factory, bus_factory):
    """Two simulated guarded drives (CSP and CSV, as the file says) and a rig for them; node
    guarding is what ``guarding: auto`` picks for them."""
    rigs: list[Rig] = []

    def make(**kw):
        nodes = can_setup.nodes[:2]
        channel = can_setup.channel(virtual_channel)
        segment = sim_segment_factory(nodes, channel=channel, interface=can_setup.interface,
                                      eds_path=GUARDED, params=can_setup.joints,
                                      sync_period=can_setup.dt)
        rig = Rig.for_setup(bus_factory(channel, can_setup.interface), nodes, can_setup,
                            modes=("csp", "csv"), drive={"eds": GUARDED}, **kw)
        rigs.append(rig)
        return segment, rig

    yield make
    for rig in rigs:
        rig.close()


def _bring_up_and_hold(rig: Rig) -> None:
    budget = rig.setup.bring_up_budget(len(rig.hw.drives_config))
    assert rig.run_until(lambda: not rig.hw.starting, budget), rig.hw.drive_status()
    assert rig.hw.all_ready, rig.hw.drive_status()
    rig.mgr.add_controller(Sine("sine", JointMode.CSP, amplitude=0.1), emergency=Brake())
    assert rig.switch("sine") == SwitchResult.SWITCHED
    assert rig.run_until(lambda: rig.hw.all_enabled, rig.setup.enable_budget()), \
        rig.hw.drive_status()


def _guarding(recorder, node: int, since: int) -> tuple[list, list]:
    """The remote requests to ``node`` and its answers, recorded since ``since``."""
    frames = recorder.frames(cia301.HEARTBEAT + node, since=since)
    return ([f for f in frames if f.message.is_remote_frame],
            [f for f in frames if not f.message.is_remote_frame])


def test_a_drive_without_heartbeat_is_guarded_by_the_cycle_and_answers_toggling(
        can_setup, rig_on, frame_recorder, virtual_channel):
    recorder = frame_recorder(can_setup.channel(virtual_channel), can_setup.interface)
    segment, rig = rig_on()
    _bring_up_and_hold(rig)
    period = rig.hw.drives_config[0].heartbeat_ms
    for sim in segment.drives.values():  # configured at bring-up, by SDO
        assert sim.od_value(cia301.GUARD_TIME) == period
        assert sim.od_value(cia301.LIFE_TIME_FACTOR) == life_time_factor(period,
                                                                         rig.hw.consumer_ms)
        assert sim.nmt_state == cia301.NmtState.OPERATIONAL
    mark = recorder.mark()
    rig.run(6 * period / 1000)
    for node in segment.drives:
        requests, answers = _guarding(recorder, node, mark)
        assert len(requests) >= 4, (node, requests)
        # each answer: OPERATIONAL, the toggle bit flipped from the answer before
        states = [f.data[0] & 0x7F for f in answers]
        toggles = [f.data[0] >> 7 for f in answers]
        assert len(answers) >= 3 and set(states) == {cia301.NmtState.OPERATIONAL}, answers
        assert all(a != b for a, b in zip(toggles, toggles[1:])), toggles
    assert rig.hw.guard_repeats == 0
    assert rig.mgr.state == ManagerState.OK
    assert "node guarding" in "\n".join(plan_drive(rig.hw.drives_config[0]).notes)


def test_a_guarded_drive_that_stops_answering_is_an_estop(rig_on):
    # TPDO supervision out of the way (a silent drive sends no TPDOs either): the guarding
    # deadline is what trips
    segment, rig = rig_on(tpdo_timeout_cycles=1_000_000)
    _bring_up_and_hold(rig)
    silent = tuple(segment.drives)[-1]
    segment.drives[silent].set_silent(True)
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget()), rig.hw.drive_status()
    latched = rig.hw.supervisor.latched[1]
    assert latched.node_id == silent and "node guarding answer lost" in latched.cause


def test_a_stopped_loop_stops_guarding_and_the_drives_switch_off_by_themselves(
        can_setup, rig_on, frame_recorder, virtual_channel):
    """The requests come from the cycle only: when it stops, each drive's life guarding
    (guard time x life time factor) times out, it sends EMCY 0x8130 and 0x6007 switches
    its power stage off."""
    recorder = frame_recorder(can_setup.channel(virtual_channel), can_setup.interface)
    segment, rig = rig_on()
    _bring_up_and_hold(rig)
    mark = synced_mark(recorder, rig)  # and the loop stops here
    stopped = time.monotonic()
    guard_ms = rig.hw.drives_config[0].heartbeat_ms
    life = guard_ms * life_time_factor(guard_ms, rig.hw.consumer_ms) / 1000
    # the last request came at most one guard time before the stop
    bound = life + guard_ms / 1000 + rig.setup.stall
    seconds_until_all_off(segment, stopped, bound)
    nodes = tuple(segment.drives)
    lost = recorder.wait_for_count(
        len(nodes), rig.setup.stall, {cia301.EMCY + n for n in nodes}, since=mark,
        where=lambda f: struct.unpack_from("<H", f.data)[0] == cia301.EMCY_HEARTBEAT)
    assert {f.cob_id - cia301.EMCY for f in lost} == set(nodes)
    assert all(d.nmt.guarding_lost for d in segment.drives.values())


def test_an_answer_whose_toggle_did_not_change_is_not_counted(can_setup, rig_on, bus_factory,
                                                               virtual_channel):
    """A second answer with the toggle bit of the one before answers no new request (a
    stale or doubled frame): it does not keep the drive alive and is counted. (Should the
    drive's own next answer come first, that one repeats the injected one's bit instead.)"""
    segment, rig = rig_on()
    _bring_up_and_hold(rig)
    node = tuple(segment.drives)[0]
    last = rig.hw.guarding._toggle[0]
    assert last in (0, cia301.GUARD_TOGGLE)
    other = bus_factory(can_setup.channel(virtual_channel), can_setup.interface)
    other.send(can.Message(arbitration_id=cia301.HEARTBEAT + node, is_extended_id=False,
                           data=bytes((last | cia301.NmtState.OPERATIONAL,))))
    guard_s = rig.hw.drives_config[0].heartbeat_ms / 1000
    assert rig.run_until(lambda: rig.hw.guard_repeats >= 1,
                         guard_s + rig.setup.cycles_budget(10))
    rig.run(3 * guard_s)
    assert rig.mgr.state == ManagerState.OK  # the real answers go on toggling


def test_one_lost_answer_is_not_taken_for_a_repeat(can_setup, rig_on, frame_recorder,
                                                   virtual_channel):
    """The drive toggles with every answer it sends: after a lost one, the next carries the
    bit of the one before it. Two requests on, that is a new answer, not a repeat."""
    recorder = frame_recorder(can_setup.channel(virtual_channel), can_setup.interface)
    segment, rig = rig_on()
    _bring_up_and_hold(rig)
    node = tuple(segment.drives)[0]
    guard_s = rig.hw.drives_config[0].heartbeat_ms / 1000
    mark = recorder.mark()
    segment.drives[node].set_silent(True)  # it hears the next request, its answer is lost
    assert rig.run_until(lambda: len(_guarding(recorder, node, mark)[0]) >= 1,
                         guard_s + rig.setup.cycles_budget(10))
    segment.drives[node].set_silent(False)
    mark = recorder.mark()
    assert rig.run_until(lambda: len(_guarding(recorder, node, mark)[1]) >= 2,
                         3 * guard_s + rig.setup.cycles_budget(10))
    assert rig.hw.guard_repeats == 0
    assert rig.mgr.state == ManagerState.OK


class HungMailbox(Responder):
    """A hung node's CAN controller: its CPU stopped, but the controller still answers each
    remote request on 0x700 + node id by itself, with the frame last loaded into its
    mailbox, the same byte every time: its toggle bit never changes."""

    def __init__(self, bus: can.BusABC, node: int, byte: int) -> None:
        self.answered = 0

        def answer(msg: can.Message) -> list[can.Message]:
            if not (msg.is_remote_frame and msg.arbitration_id == cia301.HEARTBEAT + node):
                return []
            self.answered += 1
            return frames(cia301.HEARTBEAT + node, [bytes((byte,))])
        super().__init__(bus, answer, owns_bus=False)  # the test's bus_factory shuts it


@pytest.fixture
def hung_mailbox(can_setup, bus_factory, virtual_channel):
    boxes: list[HungMailbox] = []

    def make(node: int, byte: int) -> HungMailbox:
        box = HungMailbox(bus_factory(can_setup.channel(virtual_channel), can_setup.interface),
                          node, byte)
        boxes.append(box)
        return box
    yield make
    for box in boxes:
        box.close()


def test_a_hung_node_whose_mailbox_answers_without_toggling_is_an_estop(rig_on, hung_mailbox):
    """Answers that never toggle are no sign of life, however many come: the deadline runs
    out as for a silent drive, and the cause says why the answers did not count."""
    segment, rig = rig_on(tpdo_timeout_cycles=1_000_000)  # the guarding deadline trips
    _bring_up_and_hold(rig)
    node = tuple(segment.drives)[-1]
    lead = rig.hw.drives_config.index(next(d for d in rig.hw.drives_config
                                           if d.node_id == node))
    last = rig.hw.guarding._toggle[lead]
    segment.drives[node].set_silent(True)  # its CPU hangs: nothing of its own any more
    box = hung_mailbox(node, last | cia301.NmtState.OPERATIONAL)
    assert rig.run_until(lambda: rig.mgr.state == ManagerState.EMERGENCY,
                         rig.setup.detect_budget()), rig.hw.drive_status()
    assert box.answered >= 2
    latched = rig.hw.supervisor.latched[lead]
    assert latched.node_id == node and "node guarding answer lost" in latched.cause
    assert "toggle bit did not change" in latched.cause, latched.cause
    assert rig.hw.guard_repeats >= box.answered - 1


def test_a_hung_node_is_faulted_no_later_than_a_silent_one(rig_on, hung_mailbox):
    """The deadline counts from the last answer that toggled: a mailbox answering every
    request buys the drive not one period more than silence would."""
    segment, rig = rig_on(tpdo_timeout_cycles=1_000_000)
    _bring_up_and_hold(rig)
    node = tuple(segment.drives)[0]
    lead = 0
    last = rig.hw.guarding._toggle[lead]
    segment.drives[node].set_silent(True)
    hung_mailbox(node, last | cia301.NmtState.OPERATIONAL)
    hung = time.monotonic()
    assert rig.run_until(lambda: rig.hw.supervisor.latched[lead] is not None,
                         rig.setup.detect_budget()), rig.hw.drive_status()
    timeout = rig.hw.supervisor.heartbeat_timeout[lead]
    # the last toggling answer came at most one guard period before the hang
    assert rig.hw.supervisor.latched[lead].time - hung <= timeout + rig.setup.cycles_budget(2)


# --- which answers count, without a bus: the rule itself ------------------------------------
class _Requests:
    """Where the guard requests go: counted (a port's ``send``)."""

    def __init__(self) -> None:
        self.sent = 0

    def send(self, msg: can.Message) -> None:
        self.sent += 1


OPERATIONAL = cia301.NmtState.OPERATIONAL


def _one_guarded() -> NodeGuarding:
    guarding = NodeGuarding([True], [1], [0.1], [_Requests()])
    guarding.start(0)
    return guarding


def _asked(guarding: NodeGuarding, t: float) -> float:
    guarding.send_due(t)
    return t + 0.1


def test_a_mailbox_answering_every_request_alike_counts_once():
    guarding, t = _one_guarded(), 0.0
    taken = []
    for _ in range(20):
        t = _asked(guarding, t)
        taken.append(guarding.answer(0, OPERATIONAL))
    assert taken[0] == OPERATIONAL and taken[1:] == [None] * 19
    assert guarding.repeats == 19 and guarding.stale[0] == 19
    assert "19 answers came whose toggle bit did not change" in guarding.why_lost(0)


def test_a_mailbox_answering_every_second_request_alike_is_excused_once():
    """A request without an answer before a repeat may be a lost answer: excused, once; the
    answer after it must toggle."""
    guarding, t = _one_guarded(), 0.0
    taken = []
    for k in range(20):
        t = _asked(guarding, t)
        if k % 2 == 0:
            taken.append(guarding.answer(0, OPERATIONAL | cia301.GUARD_TOGGLE))
    assert taken[:2] == [OPERATIONAL, OPERATIONAL] and set(taken[2:]) == {None}


def test_a_boot_up_starts_the_toggling_over():
    guarding, t = _one_guarded(), 0.0
    t = _asked(guarding, t)
    assert guarding.answer(0, OPERATIONAL) == OPERATIONAL
    t = _asked(guarding, t)
    assert guarding.answer(0, cia301.NmtState.BOOT_UP) == cia301.NmtState.BOOT_UP
    t = _asked(guarding, t)
    assert guarding.answer(0, cia301.NmtState.PRE_OPERATIONAL) == \
        cia301.NmtState.PRE_OPERATIONAL
    assert guarding.stale[0] == 0 and guarding.why_lost(0) == ""


@settings(max_examples=300, derandomize=True, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=60), st.integers(0, 1))
def test_answers_that_never_toggle_buy_at_most_one_excused_answer(heard, bit):
    """Whatever the pattern of requests answered and not, a constant toggle bit is taken
    at most twice: the first answer and one excused as following a lost one."""
    guarding, t = _one_guarded(), 0.0
    taken = 0
    for answered in heard:
        t = _asked(guarding, t)
        if answered:
            taken += guarding.answer(0, OPERATIONAL | bit << 7) is not None
    assert taken <= 2


@settings(max_examples=300, derandomize=True, deadline=None)
@given(st.lists(st.integers(2, 6), max_size=12), st.integers(0, 1))
def test_a_drive_that_toggles_loses_no_answer_to_an_isolated_lost_frame(runs, first):
    """A drive that toggles with every answer it sends, one answer lost now and then (each
    loss followed by at least two answers heard): every answer heard is taken."""
    guarding, t = _one_guarded(), 0.0
    toggle = first
    pattern = [True] * 3 + [x for run in runs for x in [False] + [True] * run]
    for heard in pattern:
        t = _asked(guarding, t)
        byte = OPERATIONAL | toggle << 7
        toggle ^= 1  # the drive sent it, heard or not
        if heard:
            assert guarding.answer(0, byte) == OPERATIONAL
    assert guarding.repeats == 0


# --- which way a drive is watched (check-config), without a bus ----------------------------
def _plan(eds: str | None, **kw):
    return plan_drive(DriveConfig("j1", 1, 4096, 1.0, eds=eds, **kw))


def test_auto_guards_a_drive_without_heartbeat_and_says_how_it_is_protected():
    plan = _plan(GUARDED)
    assert plan.guarded
    report = "\n".join(plan.report())
    assert "no heartbeat producer (0x1017): node guarding, the manager asks every 100 ms " \
        "(0x100C)" in report
    assert "manager loss: life guarding 0x100C/0x100D -> 0x6007 = 2: disable voltage" in report


def test_a_drive_with_a_heartbeat_keeps_it_unless_told():
    assert not _plan(None).guarded  # the shipped drive file: heartbeat producer and consumer
    with pytest.raises(ValueError, match=r"guarding: node_guarding, but .* has no writable "
                                         r"guard time and life time factor \(0x100C/0x100D\)"):
        _plan(None, guarding="node_guarding")
    assert _plan(GUARDED, guarding="node_guarding").guarded


def test_a_drive_told_heartbeat_without_one_is_refused_naming_the_object_and_the_way_out():
    with pytest.raises(ValueError, match=r"guarding: heartbeat, but .* has no writable "
                                         r"heartbeat producer \(0x1017\); it has node "
                                         r"guarding \(guarding: node_guarding\)"):
        _plan(GUARDED, guarding="heartbeat")
    with pytest.raises(ValueError, match="guarding must be one of"):
        _plan(GUARDED, guarding="nodeguarding")


def test_the_life_time_is_the_consumer_time_within_what_a_factor_can_say():
    assert life_time_factor(100, 500) == 5
    assert life_time_factor(200, 500) == 3       # rounded up: never shorter than asked
    assert life_time_factor(1000, 500) == 2      # one late request is never a loss
    assert life_time_factor(1, 65535) == 255     # UNSIGNED8
    assert math.isclose(200 * life_time_factor(200, 6000) / 1000, 6.0)
