"""A stop acts whatever it carries, on every surface that takes one (rocoma_can/stop_surfaces.py).

One running system serves every surface at once: a Runtime on python-can's virtual bus with
two simulated drives, its manager node (SDO, the e-stop COB-ID), the Zenoh bridge on a
loopback endpoint, the ROS 2 node (a Zenoh client of that endpoint) and the Foxglove live
view (served by the recording's writer process, through its front). Each case brings the
manager to OK (controller pd), sends one stop in one garbage form (an encoding nobody
expects, nothing, megabytes, wrong types, invalid UTF-8, garbage JSON, a framing no client
of ours uses) and asserts the stop acted: one
e-stop of that surface, the manager in EMERGENCY (pd has an emergency controller) or, for a
failproof stop, FAILPROOF with every drive's torque off.

The cases are built from ``SURFACES``: a surface listed there without forms here fails the
collection of this module, and a surface added elsewhere without being listed there fails
``test_no_stop_reaches_the_manager_but_through_a_surface``, which reads the sources.
"""
from __future__ import annotations

import ast
import json
import socket
import struct
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from fixtures.running import DEMO_RUN, DEMO_WAIT, runtime_running, wait_for

from rocoma_can import EventKind, ManagerEvent, ManagerState, SwitchResult
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.main import main
from rocoma_can.drivers.sim.segment import SimulatedSegment
from rocoma_can.runtime import Runtime
from rocoma_can.stop_surfaces import SURFACES, StopSurface

pytest.importorskip("foxglove")
pytest.importorskip("websockets.sync.client")
zenoh = pytest.importorskip("zenoh")
from fixtures.foxglove_viewer import SERVICE_CALL_REQUEST, Viewer  # noqa: E402 - after skips

from rocoma_can.fleet.bridge import open_session  # noqa: E402 - needs zenoh
from rocoma_can.live.foxglove import FoxgloveConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ESTOP, FAILPROOF_STOP = 0x2110, 0x2111
OBJECT = {"estop": ESTOP, "failproof": FAILPROOF_STOP}


@dataclass
class System:
    rt: Runtime
    segment: SimulatedSegment
    channel: str
    raw: can.BusABC        # a third party's frames on the drives' bus
    zenoh: Any             # an operator's Zenoh session
    prefix: str
    viewer: Viewer         # a Foxglove viewer of the live view
    stops: list[ManagerEvent]

    @property
    def node(self) -> int:
        return self.rt.config.manager.node_id


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def system() -> Iterator[System]:
    channel = f"stop-surfaces-{uuid.uuid4().hex[:8]}"
    segment = SimulatedSegment.open(channel, "virtual", (1, 2)).start()
    endpoint, prefix = f"tcp/127.0.0.1:{_free_port()}", f"rocoma/stops-{uuid.uuid4().hex[:8]}"
    cfg = demo_config(channel, drives=2, rate=100.0)
    cfg["manager"]["estop_must_be_cleared"] = False  # each case switches back at once
    cfg["zenoh"] = {"prefix": prefix, "listen": [endpoint], "multicast": False}
    # the ROS 2 node, a Zenoh client as rmw_zenoh's are, of the bridge's endpoint
    cfg["ros2"] = {"connect": [endpoint], "domain_id": ROS2_DOMAIN}
    raw = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    try:
        with runtime_running(cfg, DEMO_RUN,
                             foxglove=FoxgloveConfig(host="127.0.0.1", port=0)) as rt:
            stops: list[ManagerEvent] = []
            rt.manager.subscribe(lambda e: stops.append(e)
                                 if e.kind is EventKind.EMERGENCY_STOP else None)
            wait_for(lambda: rt.manager.switch_blocked() is None, "the drives brought up",
                     DEMO_WAIT)
            session = open_session("peer", [endpoint], [], multicast=False)
            viewer = Viewer(rt.foxglove.port)
            try:
                viewer.pump(lambda: {"/rocoma/estop", "/rocoma/failproof"} <= set(
                    viewer.services), "the stop services advertised")
                yield System(rt, segment, channel, raw, session, prefix, viewer, stops)
            finally:
                viewer.close()
                session.close()
    finally:
        raw.shutdown()
        segment.stop()
        segment.check()


# --- the surfaces' garbage forms: (name, send(system, kind)) --------------------------------
Send = Callable[[System, str], None]


def _frame(data: bytes = b"", **kw: Any) -> Send:
    def send(s: System, kind: str) -> None:
        s.raw.send(can.Message(arbitration_id=s.rt.config.manager.estop_cob_id,
                               is_extended_id=False, data=data, **kw))
    return send


def _sdo(head: Callable[[int], bytes]) -> Send:
    """A frame to the node's SDO server, ``head(object)`` its bytes."""
    def send(s: System, kind: str) -> None:
        s.raw.send(can.Message(arbitration_id=0x600 + s.node, is_extended_id=False,
                               data=head(OBJECT[kind])))
    return send


def _initiate(command: int, tail: bytes, subindex: int = 0) -> Callable[[int], bytes]:
    return lambda index: struct.pack("<BHB", command, index, subindex) + tail


def _cli(*extra: str) -> Send:
    def send(s: System, kind: str) -> None:
        assert main([kind, *extra, "--interface", "virtual", "--channel", s.channel,
                     "--node", str(s.node)]) == 0
    return send


def _zenoh(payload: bytes | None, encoding: str | None = None) -> Send:
    def send(s: System, kind: str) -> None:
        replies = list(s.zenoh.get(f"{s.prefix}/{kind}", payload=payload, encoding=encoding,
                                   timeout=DEMO_WAIT))
        assert replies and replies[0].ok is not None
        answer = json.loads(replies[0].ok.payload.to_string())
        assert answer["ok"] is True, answer
    return send


def _foxglove(encoding: bytes, payload: bytes, fragments: int = 1) -> Send:
    """A service call request as the protocol frames it (a message, or ``fragments`` WebSocket
    frames of it), whatever its encoding and payload."""
    def send(s: System, kind: str) -> None:
        v = s.viewer
        v._call += 1
        call = v._call
        message = struct.pack("<BIII", SERVICE_CALL_REQUEST,
                              v.services[f"/rocoma/{kind}"]["id"], call,
                              len(encoding)) + encoding + payload
        if fragments == 1:
            v.ws.send(message)
        else:
            step = -(-len(message) // fragments)
            v.ws.send(iter([message[k:k + step] for k in range(0, len(message), step)]))
        v.pump(lambda: call in v.answers, "the stop's answer")
        assert v.answers[call].get("ok") is True, v.answers[call]
    return send


ROS2_DOMAIN = 7


def _ros2(payload: bytes | None, encoding: str | None = None,
          attachment: bytes | None = None) -> Send:
    """A call of the ROS 2 node's Trigger service rocoma/<kind> as any client may make it
    (rmw_zenoh's service key, a query with the target a ROS 2 client uses); its answer a
    Trigger response saying success."""
    from rocoma_can.ros2.interfaces import Interfaces, dds_type_name
    ros2 = Interfaces("jazzy")
    trigger = "std_srvs/srv/Trigger"

    def send(s: System, kind: str) -> None:
        key = f"{ROS2_DOMAIN}/rocoma/{kind}/{dds_type_name(trigger)}/{ros2.hash(trigger)}"
        replies = list(s.zenoh.get(key, payload=payload, encoding=encoding,
                                   attachment=attachment,
                                   target=zenoh.QueryTarget.ALL_COMPLETE, timeout=DEMO_WAIT))
        assert replies and replies[0].ok is not None, "no answer from the ROS 2 node"
        answer = ros2.decode(replies[0].ok.payload.to_bytes(), f"{trigger}_Response")
        assert answer.success, answer.message
    return send


HOSTILE_BYTES = bytes(range(256))
INVALID_UTF8 = b"\xff\xfe\xc3("
GARBAGE_JSON = b'{"name": [1, {"pd": nul'
WRONG_TYPES = b'[1, 2.5, {"estop": null}, "\\u0000"]'

FORMS: dict[str, list[tuple[str, Send]]] = {
    "can-frame": [
        ("empty", _frame()),
        ("all-ones", _frame(b"\xff" * 8)),
        ("invalid-utf8", _frame(INVALID_UTF8)),
        ("remote", _frame(is_remote_frame=True, dlc=8)),
        ("one-zero-byte", _frame(b"\x00")),
    ],
    "sdo": [
        ("expedited-wrong-size", _sdo(_initiate(0x23, b"\xff\xff\xff\xff"))),
        ("expedited-no-size", _sdo(_initiate(0x22, INVALID_UTF8))),
        ("segmented-never-ended", _sdo(_initiate(0x21, struct.pack("<L", 7)))),
        ("segmented-oversized", _sdo(_initiate(0x21, struct.pack("<L", 1 << 20)))),
        ("block-download", _sdo(_initiate(0xC6, struct.pack("<L", 3)))),
        ("short-frame", _sdo(lambda index: _initiate(0x2F, b"")(index)[:3])),
        ("other-subindex", _sdo(_initiate(0x2F, b"\x01\x00\x00\x00", subindex=5))),
    ],
    "cli": [
        ("a-word", _cli("now")),
        ("invalid-utf8", _cli(INVALID_UTF8.decode("utf-8", "surrogateescape"))),
        ("huge", _cli("x" * 100_000)),
        ("unknown-option", _cli("--force")),
        ("empty", _cli("")),
        ("garbage-json", _cli(GARBAGE_JSON.decode())),
    ],
    "zenoh": [
        ("bytes", _zenoh(HOSTILE_BYTES)),
        ("invalid-utf8", _zenoh(INVALID_UTF8)),
        ("huge", _zenoh(b"\xff" * (1 << 20))),
        ("garbage-json", _zenoh(GARBAGE_JSON)),
        ("wrong-types", _zenoh(WRONG_TYPES, "application/json")),
        ("protobuf", _zenoh(b"\x08\x01", "application/protobuf")),
        ("empty", _zenoh(b"")),
    ],
    "foxglove": [
        ("protobuf", _foxglove(b"protobuf", b"\x08\x01")),
        ("JSON-capitals", _foxglove(b"JSON", b"{}")),
        ("no-encoding", _foxglove(b"", b"")),
        ("invalid-utf8-encoding", _foxglove(INVALID_UTF8, INVALID_UTF8)),
        ("garbage-json", _foxglove(b"json", GARBAGE_JSON)),
        ("wrong-types", _foxglove(b"json", WRONG_TYPES)),
        ("huge", _foxglove(b"cbor", b"\xff" * (2 << 20))),
        ("fragmented", _foxglove(b"msgpack", b"\x81\xa1a\x01", fragments=5)),
    ],
    "ros2": [
        ("no-payload-no-attachment", _ros2(None)),
        ("bytes", _ros2(HOSTILE_BYTES, attachment=b"\x01")),
        ("invalid-utf8", _ros2(INVALID_UTF8, "text/plain;charset=utf-8")),
        ("huge", _ros2(b"\xff" * (1 << 20))),
        ("garbage-json", _ros2(GARBAGE_JSON, "application/json", attachment=GARBAGE_JSON)),
        ("wrong-types", _ros2(WRONG_TYPES, "application/cdr")),
        ("attachment-too-long", _ros2(b"\x00\x01\x00\x00", attachment=b"\xff" * 4096)),
    ],
}

CASES = [pytest.param(surface, kind, send, id=f"{surface.name}-{kind}-{form}")
         for surface in SURFACES for kind in surface.kinds
         for form, send in FORMS[surface.name]]


def _to_ok(s: System) -> None:
    """pd active, the manager OK (from EMERGENCY or FAILPROOF: no latch in this config)."""
    m = s.rt.manager
    wait_for(lambda: m.switch_blocked() is None, "the drives ready to switch", DEMO_WAIT)
    assert m.switch_controller("pd", timeout=DEMO_WAIT) in (SwitchResult.SWITCHED,
                                                            SwitchResult.RUNNING)
    wait_for(lambda: m.state is ManagerState.OK, "the manager OK", DEMO_WAIT)


def _cycles(s: System, n: int) -> None:
    """``n`` more loop cycles."""
    start = s.rt.loop.stats.cycles
    wait_for(lambda: s.rt.loop.stats.cycles >= start + n, f"{n} cycles", DEMO_WAIT)


@pytest.mark.parametrize("surface, kind, send", CASES)
def test_a_stop_acts_whatever_it_carries(system: System, surface: StopSurface, kind: str,
                                         send: Send) -> None:
    _to_ok(system)
    _cycles(system, 2)  # the switch's own events delivered
    before = len(system.stops)
    send(system, kind)
    want = ManagerState.EMERGENCY if kind == "estop" else ManagerState.FAILPROOF
    wait_for(lambda: system.rt.manager.state is want, f"the manager in {want.name}",
             DEMO_WAIT)
    _cycles(system, 10)  # a second stop of the same request would have acted by now
    assert system.rt.manager.state is want
    causes = [e.cause for e in system.stops[before:]]
    assert len(causes) == 1, causes  # one request, one stop
    through = [s for s in SURFACES if s.name in surface.client_of] or [surface]
    assert any(causes[0].startswith(s.cause(kind)) for s in through), causes
    if kind == "failproof":
        wait_for(lambda: all(d.state402.name != "OPERATION_ENABLED"
                             for d in system.segment.drives.values()),
                 "torque off on every drive", DEMO_WAIT)


# --- the list is closed -------------------------------------------------------------------
def test_every_surface_has_garbage_forms_and_both_ways_are_listed():
    assert set(FORMS) == {s.name for s in SURFACES}
    assert len({s.name for s in SURFACES}) == len(SURFACES)
    assert all(s.kinds for s in SURFACES)


#: where a manager's emergency_stop / failproof_stop may be called: (file, function). None of
#: these is a stop request from outside; every such request goes through a StopSurface.
NOT_A_REQUEST = {
    ("rocoma_can/stop_surfaces.py", "stop"),            # the one place requests arrive
    ("rocoma_can/stop_surfaces.py", "StopSurface("),    # where the surfaces are made
    ("drivers/cycle/stop_requests.py", "apply"),              # what the cycle's read found (faults,
                                                        # and e-stop frames: CAN_FRAME's cause)
    ("rocoma_can/runtime/loop.py", "_torque_off"),      # the loop's own stop
    ("rocoma_can/fleet/bridge.py", "_on_deadman"),      # a supervision, not a request
    ("rocoma_can/cli/demo/steps.py", "second_fault"),       # the demo's walk-through: its
    ("rocoma_can/cli/demo/steps.py", "ended_by_operator"),  # steps, an operator's stop
}
STOP_CALLS = {"emergency_stop", "failproof_stop"}


class _Calls(ast.NodeVisitor):
    """(file, innermost enclosing function) of every ``.emergency_stop``/``.failproof_stop``
    call in one file."""

    def __init__(self, file: str) -> None:
        self.file, self.found, self._functions = file, set[tuple[str, str]](), ["<module>"]

    def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef) -> None:
        self._functions.append(node.name)
        self.generic_visit(node)
        self._functions.pop()

    visit_AsyncFunctionDef = visit_FunctionDef

    def visit_Call(self, node: ast.Call) -> None:
        if isinstance(node.func, ast.Attribute) and node.func.attr in STOP_CALLS:
            self.found.add((self.file, self._functions[-1]))
        name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(
            node.func, "id", "")
        if name == "StopSurface":  # a surface made where SURFACES does not list it
            self.found.add((self.file, "StopSurface("))
        self.generic_visit(node)


def _stop_calls() -> set[tuple[str, str]]:
    found: set[tuple[str, str]] = set()
    for folder in ("rocoma_can", "drivers", "controllers"):
        for path in (ROOT / folder).rglob("*.py"):
            calls = _Calls(path.relative_to(ROOT).as_posix())
            calls.visit(ast.parse(path.read_text(), str(path)))
            found |= calls.found
    return found


def test_no_stop_reaches_the_manager_but_through_a_surface():
    """A call of the manager's stop outside NOT_A_REQUEST, or a StopSurface made outside
    rocoma_can/stop_surfaces.py, is a surface that is not in SURFACES: add it there, and
    its forms here."""
    calls = _stop_calls()
    outside = sorted(calls - NOT_A_REQUEST - {
        (f, fn) for f, fn in calls if f == "rocoma_can/manager.py"})  # the manager itself
    assert not outside, f"stops that bypass rocoma_can/stop_surfaces.py: {outside}"


def test_the_garbage_forms_of_one_surface_are_not_one_form_many_times():
    for name, forms in FORMS.items():
        assert len({form for form, _ in forms}) == len(forms) >= 5, name


def test_a_stop_never_fails_for_its_kind_word():
    """StopSurface.stop: any kind but "failproof" is an e-stop."""
    calls: list[tuple[str, str]] = []

    class Manager:
        def emergency_stop(self, cause: str = "") -> None:
            calls.append(("estop", cause))

        def failproof_stop(self, cause: str = "") -> None:
            calls.append(("failproof", cause))
    for surface in SURFACES:
        for kind in ("estop", "failproof", "", "\udcff", "ESTOP"):
            surface.stop(Manager(), kind, " (test)")
    assert [k for k, _ in calls] == ["estop", "failproof", "estop", "estop", "estop"] * len(
        SURFACES)
    assert calls[1] == ("failproof", "CAN failproof stop (test)")

