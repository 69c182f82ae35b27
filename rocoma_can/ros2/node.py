"""The manager as a ROS 2 node over rmw_zenoh (docs/ros2.md): what ``ros2 topic list``,
``ros2 service list`` and ``ros2 control list_controllers`` see, with no ROS on this
machine. A Zenoh client of the router rmw_zenoh's nodes use (tcp/localhost:7447).

Publishes ``joint_states`` (every 1/joint_states_rate s), ``/diagnostics`` (every second
and on every manager event), ``/rosout`` (every e-stop, switch, clear, recovery and fault,
and every call refused, with why) and ``/rocoma/state`` (the status report as JSON, with
the diagnostics); serves
``/rocoma/estop``, ``/rocoma/failproof``, ``/rocoma/clear``, ``/rocoma/recover``
(std_srvs/Trigger: a stop acts whatever the request holds; the others under the rules of
every remote surface, rocoma_can/remote.py), ``/controller_manager/list_controllers`` and
``/controller_manager/switch_controller`` (``ros2.controller_manager`` names another
prefix, clear of ros2_control's own controller manager); subscribes to the command topic
of every controller that follows one (rocoma_can/inputs.py). Relative names are in the node's
namespace (``joint_states`` as joint_state_broadcaster's, ``rocoma/...``,
``controller_manager/...``); ``/diagnostics`` and ``/rosout`` are absolute, as ROS 2's own.

Threads: the node's publisher thread builds and sends every publication; Zenoh's threads
answer the services (a few attribute reads, a non-blocking manager call, a switch answered
when its future completes) and decode the commands. None of it runs in the cycle: the loop
costs what the fleet bridge costs it (a manager event queued). Publications are sent with
congestion control DROP, so a slow or vanished peer never makes a put wait; a publication
that could not go out when due is dropped and counted (``dropped``), and so is an event
that found the node's event queue full.
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from ..errors import RocomaError
from ..events import EventKind, ManagerEvent
from ..inputs import JointCommandSample, TopicCommanded
from ..interfaces import EmergencyController, FailproofController
from ..remote import STOPS, StopAnswers, Transport, serve, switch_target, switch_what, tell
from ..stop_surfaces import ROS2
from . import messages
from .config import Ros2Config
from .graph import (
    DEFAULT_QOS,
    PUBLISHER,
    ROSOUT_QOS,
    SERVICE_SERVER,
    SUBSCRIPTION,
    NodeName,
    Qos,
    attachment,
    qualified,
    read_attachment,
    topic_key,
)
from .interfaces import (
    DIAGNOSTIC_ARRAY,
    JOINT_STATE,
    LIST_CONTROLLERS,
    LOG,
    STRING,
    SWITCH_CONTROLLER,
    TRIGGER,
    InterfaceError,
    Interfaces,
    Service,
    dds_type_name,
)

if TYPE_CHECKING:
    from ..drivers.protocol.joints import JointState
    from ..manager import ControllerManager, SwitchResult

log = logging.getLogger(__name__)

#: manager events waiting for the publisher thread at most; more are dropped and counted
EVENT_QUEUE = 256
#: s between two diagnostics (and /rocoma/state) publications without an event
DIAGNOSTICS_PERIOD = 1.0
#: the Trigger services under /rocoma
TRIGGERS = ("estop", "failproof", "clear", "recover")
#: the most bytes of a command or a switch request the node decodes: a JointState of a
#: hundred joints is ~6 KiB; a peer's megabytes would hold the interpreter (and so the
#: loop's thread) for a good part of a second each
MAX_REQUEST = 64 * 1024


class Ros2Error(RocomaError):
    """The node cannot be served as configured (no router, rosbags missing)."""


class Ros2Node:
    """Serves one manager as a ROS 2 node (see the module). ``state``: the joint state
    the loop writes (read, never written, by the publisher thread); ``status``: the
    status report; ``buses``: each drive's bus; ``inputs``: controllers following a
    command topic; ``cycles``: the loop's cycle count."""

    def __init__(self, config: Ros2Config, manager: ControllerManager, state: JointState,
                 status: Callable[[], dict[str, Any]],
                 recover: Callable[[], Future[bool]] | None = None,
                 buses: Mapping[str, str] | None = None,
                 inputs: Sequence[TopicCommanded] = ()) -> None:
        from ..fleet.bridge import FleetError, close_session, open_session
        self.config = config
        self.manager = manager
        self._state = state
        self._status = status
        self._recover = recover
        self._buses = dict(buses or {})
        try:
            self.interfaces = Interfaces(config.distro, config.ros2_control)
        except InterfaceError as exc:
            raise Ros2Error(str(exc)) from None
        self.counters = {"published": 0, "dropped": 0, "requests": 0, "refused": 0,
                         "commands": 0, "rejected": 0, "errors": 0}
        self._count_lock = threading.Lock()  # Zenoh answers on several threads
        #: manager events, and (text) the refusals of ROS 2 calls to say on /rosout
        self._events: queue.Queue[ManagerEvent | str | None] = queue.Queue(EVENT_QUEUE)
        self._stop = threading.Event()
        self._running = False
        self._transport = Transport(ROS2, "ros2.allow_commands", config.allow_commands)
        self._stops = StopAnswers(manager, "ros2")
        #: each publisher's sequence number, as rmw_zenoh keeps one per publisher: its
        #: subscribers count a gap in a publisher's numbers as messages lost
        self._sequences: dict[str, int] = {}
        self._unsubscribe: Callable[[], None] | None = None
        self._declared: list[Any] = []
        self._thread = threading.Thread(target=self._run, name="ros2-node", daemon=True)
        try:
            self.session = open_session(config.mode, config.connect, [], False)
        except FleetError as exc:
            raise Ros2Error(
                f"ROS 2 node: {exc} (a ROS 2 machine starts its router with `ros2 run "
                "rmw_zenoh_cpp rmw_zenohd`; --zenoh-connect names another; ros2.required: "
                "false runs without the node)") from None
        try:
            self.name = NodeName(config.domain_id, str(self.session.info.zid()), config.node,
                                 config.namespace)
            self._entity = 0
            self._token(self.name.token())
            self._pubs = {topic: self._publisher(topic, kind, qos) for topic, kind, qos in (
                ("joint_states", JOINT_STATE, DEFAULT_QOS),
                ("/diagnostics", DIAGNOSTIC_ARRAY, DEFAULT_QOS),
                ("/rosout", LOG, ROSOUT_QOS),
                ("rocoma/state", STRING, DEFAULT_QOS))}
            for service in TRIGGERS:
                self._service(f"rocoma/{service}", TRIGGER, self._trigger(service))
            self._service(f"{config.controller_manager}/list_controllers", LIST_CONTROLLERS,
                          self._list_controllers)
            self._service(f"{config.controller_manager}/switch_controller", SWITCH_CONTROLLER,
                          self._switch_controller)
            by_topic: dict[str, list[TopicCommanded]] = {}
            for controller in inputs:
                by_topic.setdefault(controller.command_topic, []).append(controller)
            for topic, followers in by_topic.items():
                self._subscription(topic, followers)
        except Exception as exc:  # zenoh.ZError: a key Zenoh refuses, a session gone
            self._undeclare()
            close_session(self.session)
            raise Ros2Error(f"ROS 2 node {config.node}: declaring it failed: "
                            f"{str(exc).split(' at /')[0]}") from None

    # --- declarations ---------------------------------------------------------------------
    def _name(self, name: str) -> str:
        return qualified(self.config.namespace, name)

    def _key(self, name: str, kind: str) -> str:
        return topic_key(self.config.domain_id, self._name(name), dds_type_name(kind),
                         self.interfaces.hash(kind))

    def _token(self, key: str) -> None:
        self._declared.append(self.session.liveliness().declare_token(key))

    def _entity_token(self, kind: str, name: str, type_name: str, qos: Qos) -> None:
        self._entity += 1
        self._token(self.name.entity_token(self._entity, kind, self._name(name),
                                           dds_type_name(type_name),
                                           self.interfaces.hash(type_name), qos))

    def _publisher(self, topic: str, kind: str, qos: Qos) -> tuple[Any, str, bytes]:
        import zenoh
        publisher = self.session.declare_publisher(
            self._key(topic, kind), congestion_control=zenoh.CongestionControl.DROP)
        self._declared.append(publisher)
        self._entity_token(PUBLISHER, topic, kind, qos)
        return publisher, kind, uuid.uuid4().bytes

    def _service(self, name: str, kind: str,
                 answer: Callable[[Any, Any], None]) -> None:
        def on_query(query: Any) -> None:
            self._count("requests")
            request = read_attachment(query.attachment.to_bytes()
                                      if query.attachment is not None else None)
            try:
                answer(query, request)
            except Exception as exc:  # noqa: BLE001 - a request must not kill Zenoh's thread
                self._count("errors")
                log.warning("ros2: %s failed: %s", name, exc)
        self._declared.append(self.session.declare_queryable(self._key(name, kind), on_query,
                                                             complete=True))
        self._entity_token(SERVICE_SERVER, name, kind, DEFAULT_QOS)

    def _subscription(self, topic: str, followers: Sequence[TopicCommanded]) -> None:
        def on_sample(sample: Any) -> None:
            received = time.monotonic()
            try:
                msg = self.interfaces.decode(sample.payload.to_bytes(), JOINT_STATE,
                                             MAX_REQUEST)
            except ValueError as exc:
                self._count("rejected")
                if self.counters["rejected"] in (1, 10, 100, 1000):
                    log.warning("ros2: %s: %s", topic, exc)
                return
            command = JointCommandSample(
                tuple(msg.name), tuple(float(v) for v in msg.position),
                tuple(float(v) for v in msg.velocity), tuple(float(v) for v in msg.effort),
                received)
            self._count("commands")
            for controller in followers:
                controller.take_command(command)
        self._declared.append(self.session.declare_subscriber(self._key(topic, JOINT_STATE),
                                                              on_sample))
        self._entity_token(SUBSCRIPTION, topic, JOINT_STATE, DEFAULT_QOS)

    # --- life cycle -------------------------------------------------------------------------
    def start(self) -> Ros2Node:
        self._unsubscribe = self.manager.subscribe(self._on_event)
        self._running = True
        self._thread.start()
        return self

    def loop_stopped(self) -> None:
        """Commands other than stops are refused from now on."""
        self._running = False

    def close(self) -> None:
        from ..fleet.bridge import close_session
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._running = False
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._undeclare()
        try:
            close_session(self.session)
        except Exception as exc:  # noqa: BLE001 - the rest of the shutdown must go on
            log.warning("ros2: closing the session failed: %s", exc)

    def _undeclare(self) -> None:
        for declared in reversed(self._declared):
            try:
                declared.undeclare()
            except Exception:  # noqa: BLE001 - a session already gone
                pass
        self._declared = []

    def info(self) -> dict[str, Any]:
        """What the status report shows of the node."""
        with self._count_lock:
            counters = dict(self.counters)
        c = self.config
        return {"node": self._name(c.node), "domain_id": c.domain_id, "distro": c.distro,
                "ros2_control": self.interfaces.ros2_control, "connect": c.connect,
                "allow_commands": c.allow_commands, **counters}

    def _count(self, what: str, n: int = 1) -> None:
        with self._count_lock:
            self.counters[what] += n

    def _on_event(self, event: ManagerEvent | str) -> None:
        """The manager's dispatcher thread (an event), Zenoh's (a refusal): queued, never
        waited for."""
        try:
            self._events.put_nowait(event)
        except queue.Full:
            self._count("dropped")

    def _refused(self, service: str, why: str) -> None:
        """A call answered no: counted, and said on /rosout, where `ros2 control` sends its
        user ("check controller_manager logs") and rqt_console shows it. Refusals take half
        the event queue at most: a caller's flood of them never crowds out the manager's
        events."""
        self._count("refused")
        if self._events.qsize() < EVENT_QUEUE // 2:
            self._on_event(f"{self._name(service)} refused: {why}")
        else:
            self._count("dropped")

    # --- the publisher thread -----------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / self.config.joint_states_rate
        state = self._state
        names = list(state.names)
        next_joints = next_diagnostics = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            wait = max(0.0, min(next_joints, next_diagnostics) - now)
            try:
                event = self._events.get(timeout=wait) if wait > 0 else self._events.get_nowait()
            except queue.Empty:
                event = None
            if isinstance(event, str):
                self._log(messages.WARN, event)
            elif event is not None:
                self._log_event(event)
                next_diagnostics = time.monotonic()
            now = time.monotonic()
            if now >= next_joints:
                missed = int((now - next_joints) / period)
                if missed:  # due while the thread was held up: gone, counted
                    self._count("dropped", missed)
                next_joints += (missed + 1) * period
                self._publish("joint_states", lambda: messages.joint_state(
                    self.interfaces, time.time_ns(), names, state.position.copy(),
                    state.velocity.copy(), state.torque.copy()))
            if now >= next_diagnostics:
                next_diagnostics = now + DIAGNOSTICS_PERIOD
                self._diagnostics()

    def _diagnostics(self) -> None:
        try:
            report = self._status()
        except Exception as exc:  # noqa: BLE001 - a report that failed: counted
            self._count("errors")
            log.debug("ros2: status report failed: %s", exc)
            return
        ns = time.time_ns()
        self._publish("/diagnostics", lambda: messages.diagnostics(
            self.interfaces, ns, self._name(self.config.node), report, self._buses))
        self._publish("rocoma/state", lambda: messages.string(
            self.interfaces, json.dumps({**report, "ros2": self.info()}, default=str)))

    def _log_event(self, event: ManagerEvent) -> None:
        from ..live.messages import WARNING, event_log
        from ..record.trace import event_message
        if event.kind is EventKind.REQUEST and event.cause.startswith(f"{ROS2.label}: "):
            return  # this node's own callers: a refusal is said as such (_refused)
        text, level = event_log(event_message(event))
        self._log(messages.WARN if level == WARNING else messages.INFO, text)

    def _log(self, level: int, text: str) -> None:
        self._publish("/rosout", lambda: messages.log(
            self.interfaces, time.time_ns(), self._name(self.config.node)[1:].replace("/", "."),
            level, text))

    def _publish(self, topic: str, build: Callable[[], bytes]) -> None:
        publisher, _, gid = self._pubs[topic]
        try:
            payload = build()
            sequence = self._sequences[topic] = self._sequences.get(topic, 0) + 1
            publisher.put(payload, attachment=attachment(sequence, gid))
            self._count("published")
        except Exception as exc:  # noqa: BLE001 - Zenoh down: counted, the manager runs on
            self._count("errors")
            if self.counters["errors"] in (1, 10, 100, 1000):
                log.warning("ros2: publishing %s failed (%d errors so far): %s", topic,
                            self.counters["errors"], exc)

    # --- services (Zenoh's threads) -----------------------------------------------------------
    def _reply(self, query: Any, request: Any, payload: bytes) -> None:
        """Answer with the request's sequence number and GID, a new timestamp; a client gone
        is counted, never raised into Zenoh (a stop it asked for has happened already)."""
        try:
            try:
                query.reply(query.key_expr, payload, attachment=attachment(
                    request.sequence if request else 0, request.gid if request else bytes(16)))
            finally:
                query.drop()
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError: the client went away
            self._count("errors")
            log.debug("ros2: answering %s failed: %s", query.key_expr, exc)

    def _trigger(self, service: str) -> Callable[[Any, Any], None]:
        def answer(query: Any, request: Any) -> None:
            def reply(result: dict[str, Any]) -> None:
                text = result.get("error") or f"state {result.get('state')}" + (
                    " (the loop had not acted on it yet)" if result.get("pending") else "")
                if result.get("ok") is False:
                    self._refused(f"rocoma/{service}", text)
                self._reply(query, request, messages.trigger_response(
                    self.interfaces, bool(result.get("ok")), text))
            # A stop acts whatever the request holds: its payload is never read.
            if service in STOPS:
                self._stops.answer(service, self._transport, self._running, reply)
            else:
                reply(serve(self.manager, service, self._transport, self._running,
                            self._recover))
        return answer

    def _list_controllers(self, query: Any, request: Any) -> None:
        m = self.manager
        running = m.active_controller_name
        listed = []
        for name, adapter in m.adapters().items():
            controller = adapter.controller
            layer = ("failproof/" if isinstance(controller, FailproofController)
                     else "emergency/" if isinstance(controller, EmergencyController) else "")
            listed.append((name, f"rocoma_can/{layer}{type(controller).__name__}",
                           "active" if name == running else "inactive"))
        self._reply(query, request, messages.controller_list(self.interfaces, listed))

    def _switch_controller(self, query: Any, request: Any) -> None:
        what = ["switch"]  # (what the audit trail is told: the name, once it is read)

        def reply(ok: bool, result: str, error: str = "") -> None:
            message = f"{result}: {error}" if error else result
            if not ok:
                self._refused(f"{self.config.controller_manager}/switch_controller", message)
            tell(self.manager, self._transport, what[0],
                 {"result": result, **({"error": error} if error else {})})
            self._reply(query, request, messages.switch_response(self.interfaces, ok, message))
        try:
            raw = query.payload.to_bytes() if query.payload is not None else b""
            msg = self.interfaces.decode(raw, Service(SWITCH_CONTROLLER).request, MAX_REQUEST)
        except ValueError as exc:
            reply(False, "ERROR", str(exc))
            return
        activate = list(msg.activate_controllers)
        if activate:
            what[0] = switch_what(activate[0].encode())
        wrong = ("" if len(activate) == 1 else
                 f"{len(activate)} controllers to activate; this manager runs one at a time"
                 " (activate exactly one: the one running is deactivated)")
        name, refusal = switch_target(self.manager, (activate[0] if activate else "").encode(),
                                      self._transport, self._running, wrong)
        if name is None:
            reply(False, refusal["result"], refusal["error"])
            return

        def done(future: Future[SwitchResult]) -> None:
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - answered, not raised in the switcher
                reply(False, "ERROR", f"{type(exc).__name__}: {exc}")
                return
            reply(result.name in ("SWITCHED", "RUNNING"), result.name,
                  self.manager.last_refusal if result.name == "ERROR" else "")
        self.manager.request_switch(name).add_done_callback(done)


def describe_node(node: Ros2Node) -> str:
    """The line ``run`` prints."""
    c = node.config
    return (f"ROS 2 node {node.info()['node']} (domain {c.domain_id}, {c.distro}, "
            f"controller_manager_msgs of ros2_control {node.interfaces.ros2_control}) via "
            f"Zenoh {c.mode} of {', '.join(c.connect)}; clear/recover/switch "
            f"{'allowed' if c.allow_commands else 'refused'}")
