"""rocoma_can/fleet/bridge.py, client.py: the manager on Zenoh (issue: beyond one machine): a real
Runtime on python-can's virtual bus with simulated drives, served on a loopback endpoint (multicast
scouting off), and a second Zenoh session, or the CLI, as the operator elsewhere. Also a demo
process killed outright, whose liveliness token must vanish."""
from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml
import zenoh
from fixtures.running import DEMO_WAIT, free_port, runtime_running
from fixtures.running import wait_for as wait_until

from rocoma_can import Controller, ManagerState
from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.main import main
from rocoma_can.fleet.bridge import FleetError, open_session
from rocoma_can.runtime import Runtime
from rocoma_can.runtime.config import validate

RATE = 100.0
BIN = Path(sys.executable).parent / "rocoma-can"


def wait_for(predicate, what: str, timeout: float = DEMO_WAIT) -> None:
    wait_until(predicate, what, timeout)


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def prefix() -> str:
    return f"rocoma/test-{uuid.uuid4().hex[:8]}"


@contextmanager
def manager(channel: str, endpoint: str, prefix: str, controllers=(), **zenoh_section):
    cfg = demo_config(channel, drives=2, rate=RATE)
    cfg["controllers"] += list(controllers)
    cfg["zenoh"] = {"prefix": prefix, "listen": [endpoint], "multicast": False,
                    "alive_timeout": 0.5, "drives_period": 0.2, **zenoh_section}
    with runtime_running(cfg, DEMO_WAIT) as rt:
        yield rt


@pytest.fixture
def operator(endpoint):
    """A second Zenoh session, as on another machine."""
    sessions = []

    def connect():
        s = open_session("peer", [endpoint], [], multicast=False)
        sessions.append(s)
        return s
    yield connect
    for s in sessions:
        s.close()


def kind(sample) -> str:
    return "PUT" if sample.kind == zenoh.SampleKind.PUT else "DELETE"


def ask(session, key: str, payload: str | None = None, timeout: float = DEMO_WAIT) -> dict:
    """One query, answered within ``timeout`` (a switch answers when it is done); asked
    again only while no queryable is known yet (a session just connected)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for reply in session.get(key, payload=payload, timeout=deadline - time.monotonic()):
            assert reply.ok is not None, reply.err.payload.to_string()
            return json.loads(reply.ok.payload.to_string())
        time.sleep(0.05)
    raise AssertionError(f"no answer on {key}")


def test_status_switch_estop_and_state_publications_in_order(
        virtual_channel, sim_segment_factory, endpoint, prefix, operator, bus_factory):
    segment = sim_segment_factory(2)
    probe = bus_factory()
    with manager(virtual_channel, endpoint, prefix, allow_commands=True) as rt:
        z = operator()
        states: list[dict] = []
        z.declare_subscriber(f"{prefix}/state",
                             lambda s: states.append(json.loads(s.payload.to_string())))
        drives: list[dict] = []
        z.declare_subscriber(f"{prefix}/drives",
                             lambda s: drives.append(json.loads(s.payload.to_string())))
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        status = ask(z, f"{prefix}/status")
        assert status["state"] == "FAILPROOF" and status["latched"] is True
        assert [d["name"] for d in status["drives"]] == ["joint1", "joint2"]
        assert status["controllers"] == ["pd", "trajectory"]
        assert status["zenoh"]["prefix"] == prefix and status["cycle"]["cycles"] > 0

        assert ask(z, f"{prefix}/clear") == {"ok": True, "state": "FAILPROOF"}
        hostile = ask(z, f"{prefix}/switch", "x" * 100_000)  # echoed back shortened
        assert hostile["result"] == "NOT_FOUND", hostile["result"]
        assert "(100000 characters)" in hostile["error"] and len(hostile["error"]) < 200, \
            hostile["error"][:300]
        for number in ("9" * 5000, "\u00b2", "0"):  # no controller number: NOT_FOUND too
            assert ask(z, f"{prefix}/switch", number)["result"] == "NOT_FOUND", number[:20]
        assert ask(z, f"{prefix}/switch", "pd") == {"result": "SWITCHED"}
        assert rt.manager.state is ManagerState.OK and rt.manager.active_controller_name == "pd"
        wait_for(lambda: rt.hardware.all_enabled, "the drives enabled")
        # the answer says what the stop did: the loop acted on it before it was given
        assert ask(z, f"{prefix}/estop") == {"ok": True, "state": "EMERGENCY"}
        probe_seen: set[int] = set()
        while probe.recv(0) is not None:  # what came before (bring-up's torque-off too)
            pass
        # in EMERGENCY: failproof torque-off
        assert ask(z, f"{prefix}/estop") == {"ok": True, "state": "FAILPROOF"}
        deadline = time.monotonic() + DEMO_WAIT
        while probe_seen != {0x201, 0x202} and time.monotonic() < deadline:
            msg = probe.recv(0.1)
            if msg is not None and msg.arbitration_id in (0x201, 0x202) \
                    and msg.data[0] == msg.data[1] == 0:
                probe_seen.add(msg.arbitration_id)
        assert probe_seen == {0x201, 0x202}  # controlword 0x0000 to both drives on the bus
        wait_for(lambda: all(d.state402.name != "OPERATION_ENABLED"
                             for d in segment.drives.values()), "the drives switched off")
        def changes() -> list[str]:
            return [s["state"] for s in states if s["kind"] == "state_changed"]
        wait_for(lambda: len(changes()) >= 4, "the publications up to the failproof stop")
        stops = [(s["state"], s["cause"]) for s in states if s["kind"] == "emergency_stop"]
        assert stops == [("EMERGENCY", "Zenoh e-stop"), ("FAILPROOF", "Zenoh e-stop")]
        assert changes() == ["FAILPROOF", "OK", "EMERGENCY", "FAILPROOF"], states  # clear first
        assert states[0]["cause"] == "emergency stop cleared"
        assert [s["time"] for s in states] == sorted(s["time"] for s in states)
        wait_for(lambda: len(drives) >= 2, "two drives publications")
        assert [d["name"] for d in drives[-1]["drives"]] == ["joint1", "joint2"]


def test_a_refused_switch_says_why_and_an_estop_is_still_accepted(
        virtual_channel, sim_segment_factory, endpoint, prefix, operator):
    sim_segment_factory(2)
    with manager(virtual_channel, endpoint, prefix) as rt:  # allow_commands: false
        z = operator()
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        answer = ask(z, f"{prefix}/switch", "pd")
        assert answer["result"] == "ERROR" and "zenoh.allow_commands: false" in answer["error"]
        assert ask(z, f"{prefix}/clear")["ok"] is False
        assert rt.manager.estop_latched and rt.manager.active_controller_name == "torque_off"
        assert ask(z, f"{prefix}/estop")["ok"] is True
        assert ask(z, f"{prefix}/status")["zenoh"]["refused"] == 2


def test_the_cli_acts_through_zenoh(virtual_channel, sim_segment_factory, endpoint, prefix,
                                    capsys):
    sim_segment_factory(2)
    opts = ["--zenoh", prefix, "--zenoh-connect", endpoint, "--zenoh-no-multicast"]
    with manager(virtual_channel, endpoint, prefix, allow_commands=True) as rt:
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        assert main(["clear", *opts]) == 0
        assert main(["switch", "nope", *opts]) == 1
        assert main(["switch", "pd", *opts]) == 0
        assert main(["list", *opts]) == 0
        assert main(["switch", "2", *opts]) == 0  # by its number in the list
        assert main(["status", "--json", *opts]) == 0
        out = capsys.readouterr().out
        assert out.startswith("clear requested\nNOT_FOUND\nSWITCHED\n1 pd\n2 trajectory\n"
                              "SWITCHED\n")
        assert json.loads(out[out.index("{"):])["active"] == "trajectory"
        assert main(["fleet", "--zenoh-connect", endpoint, "--zenoh-no-multicast",
                     "--wait", "1"]) == 0
        assert f"{prefix}: OK, trajectory, 2 drives" in capsys.readouterr().out
        assert main(["estop", *opts]) == 0
        wait_for(lambda: rt.manager.state is not ManagerState.OK, "the e-stop")


def test_the_cli_reaches_the_configs_prefix_and_each_request_is_published(
        virtual_channel, sim_segment_factory, endpoint, prefix, operator, tmp_path, capsys):
    """``-c robot.yaml --zenoh``: the prefix the config names; each request through Zenoh is
    an event on <prefix>/state (kind request: the audit trail), a refusal with its reason;
    an unknown controller gets the nearest one."""
    sim_segment_factory(2)
    config = tmp_path / "robot.yaml"
    config.write_text(yaml.safe_dump({"bus": {"interface": "virtual", "channel": "elsewhere"},
                                      "zenoh": {"prefix": prefix}}))
    opts = ["-c", str(config), "--zenoh", "--zenoh-connect", endpoint, "--zenoh-no-multicast"]
    with manager(virtual_channel, endpoint, prefix, allow_commands=True) as rt:
        z = operator()
        states: list[dict] = []
        z.declare_subscriber(f"{prefix}/state",
                             lambda s: states.append(json.loads(s.payload.to_string())))
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        assert main(["clear", *opts]) == 0
        assert main(["switch", "trajectry", *opts]) == 1
        assert capsys.readouterr().err.endswith(", did you mean 'trajectory'?\n")
        assert main(["switch", "pd", *opts]) == 0

        def requests() -> list[str]:
            return [s["cause"] for s in states if s["kind"] == "request"]
        wait_for(lambda: len(requests()) >= 3, "the requests published")
    assert requests() == [
        "Zenoh: clear: the e-stop latch is cleared",
        "Zenoh: switch to 'trajectry': NOT_FOUND: no controller 'trajectry' (controllers: pd, "
        "trajectory)",
        "Zenoh: switch to 'pd': SWITCHED"]


def test_the_alive_token_vanishes_when_the_loop_stops(virtual_channel, sim_segment_factory,
                                                      endpoint, prefix, operator):
    sim_segment_factory(2)
    events: list[tuple[str, str]] = []
    with manager(virtual_channel, endpoint, prefix) as rt:
        z = operator()
        z.liveliness().declare_subscriber(
            f"{prefix}/alive", lambda s: events.append((str(s.key_expr), kind(s))),
            history=True)
        wait_for(lambda: ("rocoma" in str(events)), "the alive token")
        assert events == [(f"{prefix}/alive", "PUT")]
        rt.loop.stop("test")
        wait_for(lambda: len(events) == 2, "the token withdrawn")
        assert events[1] == (f"{prefix}/alive", "DELETE")


class Stall(Controller):
    """A controller whose advance blocks while ``STALL`` is set: a hung loop."""

    def create(self, dt: float) -> bool:
        return True

    def initialize(self, dt: float) -> bool:
        return True

    def advance(self, dt: float) -> bool:
        while STALL.is_set():
            time.sleep(0.01)
        return True


STALL = threading.Event()


def test_the_alive_token_goes_while_the_loop_hangs_and_comes_back(
        virtual_channel, sim_segment_factory, endpoint, prefix, operator):
    """A controller stuck in advance holds the loop: the token is withdrawn after
    alive_timeout (the manager's hang watchdog, tested with the loop, sends torque-off
    meanwhile), and returns when the loop does."""
    sim_segment_factory(2)
    events: list[str] = []
    extra = {"name": "stall", "plugin": f"{__name__}:Stall"}
    with manager(virtual_channel, endpoint, prefix, allow_commands=True,
                 controllers=[extra]) as rt:
        z = operator()
        z.liveliness().declare_subscriber(f"{prefix}/alive",
                                          lambda s: events.append(kind(s)), history=True)
        wait_for(lambda: rt.hardware.all_ready and events == ["PUT"], "the alive token")
        assert ask(z, f"{prefix}/clear")["ok"]
        assert ask(z, f"{prefix}/switch", "stall") == {"result": "SWITCHED"}
        STALL.set()
        try:
            wait_for(lambda: events == ["PUT", "DELETE"], "the token withdrawn")
        finally:
            STALL.clear()
        wait_for(lambda: events == ["PUT", "DELETE", "PUT"], "the token back")


def test_the_dead_man_estops_when_the_operators_token_vanishes(
        virtual_channel, sim_segment_factory, endpoint, prefix, operator):
    sim_segment_factory(2)
    console = f"{prefix}/operators/console1"
    with manager(virtual_channel, endpoint, prefix, deadman=console,
                 allow_commands=True) as rt:
        z = operator()
        token = z.liveliness().declare_token(console)
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        wait_for(lambda: rt.fleet is not None and rt.fleet.deadman_seen, "the operator seen")
        assert ask(z, f"{prefix}/clear")["ok"] and ask(z, f"{prefix}/switch", "pd") == {
            "result": "SWITCHED"}
        token.undeclare()
        wait_for(lambda: rt.manager.state is not ManagerState.OK, "the dead-man's e-stop")
        wait_for(lambda: ask(z, f"{prefix}/status")["estop_cause"]
                 == f"Zenoh dead-man: {console} vanished", "status saying the dead-man")


def test_zenoh_unavailable_is_an_error_or_a_warning_as_configured(virtual_channel, prefix,
                                                                 caplog):
    nobody = f"tcp/127.0.0.1:{free_port()}"
    cfg = demo_config(virtual_channel, drives=2, rate=RATE)
    cfg["zenoh"] = {"prefix": prefix, "mode": "client", "connect": [nobody],
                    "multicast": False}
    with pytest.raises(FleetError, match=f"could not be opened: Unable to connect.*{nobody}"):
        Runtime(validate(cfg))
    cfg["zenoh"]["required"] = False
    with Runtime(validate(cfg)) as rt:
        assert rt.fleet is None and "Unable to connect" in rt.fleet_error
        summary = rt.run(duration=0.3, signals=False)
        assert summary.cycles > 0  # the loop runs without Zenoh
        assert rt.status()["zenoh"] == {"error": rt.fleet_error}
    assert "running without Zenoh" in caplog.text


def test_a_killed_demo_process_loses_its_alive_token(endpoint, operator):
    """kill -9: no shutdown code runs; the token goes with the process's session."""
    proc = subprocess.Popen([str(BIN), "demo", "--no-record", "--drives", "2", "--duration",
                             "120", "--zenoh-listen", endpoint], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        host, port = endpoint.removeprefix("tcp/").split(":")
        deadline = time.monotonic() + 60.0  # a process start on a loaded machine
        while proc.poll() is None and time.monotonic() < deadline:
            try:  # the demo listens once its Runtime is built
                socket.create_connection((host, int(port)), timeout=1.0).close()
                break
            except OSError:
                time.sleep(0.2)
        z = operator()
        events: list[str] = []
        z.liveliness().declare_subscriber("rocoma/demo/alive",
                                          lambda s: events.append(kind(s)), history=True)
        wait_for(lambda: events or proc.poll() is not None, "the demo's alive token")
        assert events and events[0] == "PUT", f"no token; demo rc {proc.poll()}"
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        wait_for(lambda: "DELETE" in events, "the token gone with the process")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


#: payloads no client of ours sends; each service is asked with each of them
HOSTILE = {
    "bytes": bytes(range(256)),
    "invalid-utf8": b"\xff\xfe\xc3(",
    "huge": b"\xff" * (1 << 20),
    "garbage-json": b'{"name": [1, {"pd": nul',
    "empty": b"",
}

CONTROLLERS = "pd, trajectory"


def _enabled_in_pd(rt, z, prefix: str) -> None:
    """Clear the start-up latch and run pd with every drive enabled: a stop has something to
    stop."""
    wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
    assert ask(z, f"{prefix}/clear")["ok"] is True
    assert ask(z, f"{prefix}/switch", "pd") == {"result": "SWITCHED"}
    wait_for(lambda: rt.hardware.all_enabled, "the drives enabled")


@pytest.mark.parametrize("payload", HOSTILE.values(), ids=HOSTILE.keys())
@pytest.mark.parametrize("service, state, cause", [
    ("estop", "EMERGENCY", "Zenoh e-stop"),
    ("failproof", "FAILPROOF", "Zenoh failproof stop")])
def test_a_stop_acts_whatever_its_payload(virtual_channel, sim_segment_factory, endpoint,
                                          prefix, operator, service, state, cause, payload):
    segment = sim_segment_factory(2)
    with manager(virtual_channel, endpoint, prefix, allow_commands=True) as rt:
        z = operator()
        _enabled_in_pd(rt, z, prefix)
        answer = ask(z, f"{prefix}/{service}", payload)
        assert answer["ok"] is True and set(answer) == {"ok", "state"}, answer
        wait_for(lambda: rt.manager.state.name == state, f"the manager in {state}")
        assert rt.manager.estop_latched
        # the status is the loop's snapshot: it says the cause within a cycle or a few
        wait_for(lambda: ask(z, f"{prefix}/status")["estop_cause"] == cause,
                 f"status saying {cause!r}")
        wait_for(lambda: all(d.state402.name != "OPERATION_ENABLED"
                             for d in segment.drives.values()), "torque off on every drive")


def _expected(service: str, name: str) -> dict:
    """What the manager answers ``service`` with when asked with HOSTILE[name]."""
    payload = HOSTILE[name]
    if service == "clear":
        return {"ok": True, "state": "FAILPROOF"}  # clear takes no payload
    if service == "recover":
        return {"ok": True, "state": "FAILPROOF", "recovery": "started"}
    try:
        text = payload.decode()
    except UnicodeDecodeError:
        return {"result": "NOT_FOUND",
                "error": f"no controller: the payload is {len(payload)} bytes that are not "
                         f"UTF-8 text (controllers: {CONTROLLERS})"}
    return {"result": "NOT_FOUND", "error": f"no controller {text!r} (controllers: "
                                            f"{CONTROLLERS})"}


@pytest.mark.parametrize("payload", HOSTILE, ids=HOSTILE.keys())
@pytest.mark.parametrize("service", ["status", "switch", "clear", "recover"])
def test_every_other_service_answers_in_its_shape_whatever_the_payload(
        virtual_channel, sim_segment_factory, endpoint, prefix, operator, service, payload):
    sim_segment_factory(2)
    with manager(virtual_channel, endpoint, prefix, allow_commands=True) as rt:
        z = operator()
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        answer = ask(z, f"{prefix}/{service}", HOSTILE[payload])
        if service == "status":
            assert answer["state"] == "FAILPROOF" and answer["active"] == "torque_off"
            assert answer["controllers"] == ["pd", "trajectory"]
        else:
            assert answer == _expected(service, payload)
        assert ask(z, f"{prefix}/status")["zenoh"]["errors"] == 0
        assert rt.manager.active_controller_name == "torque_off"  # nothing switched


@pytest.mark.parametrize("payload", ["invalid-utf8", "huge"])
def test_a_refused_switch_is_refused_before_its_payload_is_read(
        virtual_channel, sim_segment_factory, endpoint, prefix, operator, payload):
    sim_segment_factory(2)
    with manager(virtual_channel, endpoint, prefix) as rt:  # allow_commands: false
        z = operator()
        wait_for(lambda: rt.hardware.all_ready, "every drive brought up")
        assert ask(z, f"{prefix}/switch", HOSTILE[payload]) == {
            "result": "ERROR",
            "error": "switch over Zenoh is not allowed by this manager's config "
                     "(zenoh.allow_commands: false); e-stop and failproof are"}


@contextmanager
def foreign(endpoint: str, prefix: str, answer: bytes):
    """Another program serving a manager's keys: every query answered with ``answer``."""
    session = open_session("peer", [], [endpoint], multicast=False)

    def reply(query) -> None:
        query.reply(query.key_expr, answer)
        query.drop()
    queryable = session.declare_queryable(f"{prefix}/**", reply)
    try:
        yield
    finally:
        queryable.undeclare()
        session.close()


@pytest.mark.parametrize("answer, said", [
    (b"\xff\xfe", "not a rocoma-can manager's answer: b'\\xff\\xfe'"),
    (b"[1, 2]", "not a rocoma-can manager's answer: [1, 2]"),
    (b'{"state": "OK"}', "not a rocoma-can manager's answer (no 'ok'): {'state': 'OK'}"),
    (b"\x00" * 4096, "not a rocoma-can manager's answer: b'" + "\\x00" * 20
     + "'... (4096 bytes)"),
], ids=["invalid-utf8", "a-list", "no-ok", "huge"])
def test_the_cli_says_in_one_line_when_the_answer_is_not_a_managers(endpoint, prefix, capsys,
                                                                   answer, said):
    """Another program on the manager's keys: the e-stop is reported as failed (exit 1) with
    why, in one line."""
    opts = ["--zenoh", prefix, "--zenoh-connect", endpoint, "--zenoh-no-multicast"]
    with foreign(endpoint, prefix, answer):
        assert main(["estop", *opts]) == 1
    assert capsys.readouterr().err == f"rocoma-can: {prefix}/estop: {said}\n"
