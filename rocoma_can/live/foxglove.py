"""``run --foxglove``: the manager live in Foxglove, on a Foxglove
WebSocket served by foxglove-sdk (extra ``foxglove``), loopback by default.

Channels: messages.py's, each JSON with its JSON schema. ``/joint_states``,
``/rocoma/manager`` and (with a URDF) ``/tf`` every ``1/rate`` s; ``/rocoma/status`` every
``status_period`` s; ``/rocoma/log`` on every manager event (e-stop, state change, switch)
and every command called here; ``/robot_description`` whenever a viewer subscribes to it
(a WebSocket keeps nothing for a late subscriber, and the 3D panel needs it once).

Services (JSON request and answer, as the Zenoh bridge's, rocoma_can/remote.py):
``/rocoma/switch`` (request: ``{"controller": NAME}``), ``/rocoma/estop``,
``/rocoma/failproof``, ``/rocoma/clear``, ``/rocoma/recover``. A stop is obeyed from anyone;
switch, clear and recover only with ``allow_commands``.

The loop never publishes: the view's sampler thread copies from the joint state arrays the
loop writes in place (each array whole, under the GIL; position and velocity may come from
neighbouring cycles) and from plain counters, at its own rate. The manager's events reach
it through a bounded queue (full: dropped, counted). Each client has a bounded outbox in
the SDK (``backlog`` messages; full: messages for it are dropped, never waited for, and
each time the SDK says so it is counted as ``viewer_drops``), so a slow or vanished
viewer costs the loop nothing.
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, cast

from ..errors import RocomaError
from ..events import EventKind, ManagerEvent
from ..remote import COMMANDS, Transport, serve, switch_target
from . import messages
from .messages import INFO, WARNING, Channel

if TYPE_CHECKING:
    from foxglove.websocket import ServerListener

    from ..manager import ControllerManager
    from .urdf import Robot

log = logging.getLogger(__name__)

DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8765
#: events waiting for the sampler; more are dropped and counted
EVENT_QUEUE = 256
#: how long a switch service call waits for the switch's result (the switcher's own
#: timeouts end it sooner)
SWITCH_WAIT = 10.0
#: the demo's layout (docs/foxglove.md): Foxglove's "Import from file"
LAYOUT = Path(__file__).with_name("foxglove_layout.json")


class FoxgloveError(RocomaError):
    """The live view cannot be served (foxglove-sdk missing, the address taken)."""


@dataclass
class FoxgloveConfig:
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    rate: float = 30.0           # Hz: /joint_states and /rocoma/manager
    status_period: float = 0.5   # s between /rocoma/status messages
    allow_commands: bool = False  # switch, clear, recover from Foxglove
    backlog: int = 256           # messages per client before messages to it are dropped


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST``, ``:PORT`` or ``[IPV6]:PORT``; ValueError says what is wrong."""
    host, port = text, ""
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else rest
    elif text.count(":") == 1:
        host, port = text.split(":")
    host = host or DEFAULT_HOST
    if not port:
        return host, DEFAULT_PORT
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"expected HOST:PORT with a port 0..65535, got {text!r}")
    return host, int(port)


class JointSource(Protocol):
    """What the view reads of the joints (drivers.joints.JointState, written in place)."""
    names: tuple[str, ...]

    @property
    def position(self) -> Any: ...
    @property
    def velocity(self) -> Any: ...
    @property
    def torque(self) -> Any: ...


class _Subscriptions:
    """The SDK's server listener: a viewer subscribing to the robot description wants it
    sent (on the SDK's thread: the sampler sends it)."""

    def __init__(self) -> None:
        self.description_wanted = threading.Event()

    def on_subscribe(self, client: object, channel: Any) -> None:
        if channel.topic == messages.ROBOT_DESCRIPTION.topic:
            self.description_wanted.set()

    def on_unsubscribe(self, client: object, channel: Any) -> None:
        """Nothing to do; the SDK calls it on every unsubscribe and disconnect, and logs
        an error where a listener lacks it."""


#: the SDK's logger for a viewer whose outbox is full: each record is messages dropped
#: for that viewer (the SDK drops, it never waits)
LOSSY_LOGGER = "foxglove.websocket.connected_client.send_lossy"


class _Drops(logging.Handler):
    """Counts the SDK's "outbox for client ... full" records (on its threads)."""

    def __init__(self, count: Callable[[str], None]) -> None:
        super().__init__(logging.INFO)
        self._count = count

    def emit(self, record: logging.LogRecord) -> None:
        if "full" in record.getMessage():
            self._count("viewer_drops")


class FoxgloveView:
    """Serves one manager on a Foxglove WebSocket (see the module). ``status``: what
    ``rocoma-can status --json`` prints; ``counts``: the loop's (cycles, overruns);
    ``robot``: the config's URDF (None: no 3D robot)."""

    def __init__(self, config: FoxgloveConfig, manager: ControllerManager,
                 joints: JointSource, status: Callable[[], dict[str, Any]],
                 counts: Callable[[], tuple[int, int]],
                 recover: Callable[[], Future[bool]] | None = None,
                 robot: Robot | None = None) -> None:
        try:
            import foxglove
            from foxglove.websocket import Capability
        except ImportError:
            raise FoxgloveError("--foxglove needs foxglove-sdk: pip install "
                                "'rocoma-can[foxglove]'") from None
        self.config = config
        self.manager = manager
        self._joints = joints
        self._status = status
        self._counts = counts
        self._recover = recover
        self.robot = robot
        self._transport = Transport("Foxglove", "--foxglove-allow-commands",
                                    config.allow_commands)
        self.counters = {"published": 0, "events_dropped": 0, "viewer_drops": 0, "calls": 0,
                         "refused": 0, "errors": 0}
        self._count_lock = threading.Lock()  # service calls come on the SDK's threads
        self._events: queue.Queue[ManagerEvent] = queue.Queue(EVENT_QUEUE)
        self._cause = ""
        self._running = False
        self._stop = threading.Event()
        self._unsubscribe: Callable[[], None] | None = None
        self._context = foxglove.Context()
        served = messages.MANAGER_CHANNELS + (messages.ROBOT if robot is not None else ())
        self.topics = [c.topic for c in served]
        self._channels = {c.topic: foxglove.Channel(c.topic, schema=c.schema,
                                                    context=self._context) for c in served}
        self._subscriptions = _Subscriptions()
        # the SDK says of a viewer's full outbox at INFO: heard here whatever the log level
        self._drops = _Drops(self._count)
        lossy = logging.getLogger(LOSSY_LOGGER)
        lossy.addHandler(self._drops)
        if not lossy.isEnabledFor(logging.INFO):
            lossy.setLevel(logging.INFO)
        request = foxglove.MessageSchema(encoding="json", schema=foxglove.Schema(
            name="rocoma.Request", encoding="jsonschema", data=b""))
        services = [foxglove.Service(f"/rocoma/{name}", schema=foxglove.ServiceSchema(
            f"rocoma.{name}", request=request), handler=self._handler(name))
            for name in COMMANDS]
        try:
            self.server = foxglove.start_server(
                name="rocoma-can", host=config.host, port=config.port,
                capabilities=[Capability.Services], supported_encodings=["json"],
                services=services, context=self._context,
                server_listener=cast("ServerListener", self._subscriptions),
                message_backlog_size=config.backlog)
        except Exception as exc:  # the SDK's RuntimeError: the address taken or unknown
            logging.getLogger(LOSSY_LOGGER).removeHandler(self._drops)
            raise FoxgloveError(f"Foxglove: cannot serve on {config.host}:{config.port}: "
                                f"{exc}") from None
        self._thread = threading.Thread(target=self._run, name="foxglove-view", daemon=True)

    @property
    def port(self) -> int:
        """The port served (``port: 0`` picks a free one)."""
        return self.server.port

    def start(self) -> FoxgloveView:
        self._unsubscribe = self.manager.subscribe(self._on_event)
        self._running = True
        self._thread.start()
        return self

    def loop_stopped(self) -> None:
        """Commands other than stops are refused from now on."""
        self._running = False

    def close(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._running = False
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self.server.stop()
        logging.getLogger(LOSSY_LOGGER).removeHandler(self._drops)

    def info(self) -> dict[str, Any]:
        """What the status report and /rocoma/manager show of the view."""
        with self._count_lock:
            return {"address": f"{self.config.host}:{self.port}",
                    "allow_commands": self.config.allow_commands, **self.counters}

    def _count(self, what: str) -> None:
        with self._count_lock:
            self.counters[what] += 1

    # --- the manager's event thread -------------------------------------------------------
    def _on_event(self, event: ManagerEvent) -> None:
        try:
            self._events.put_nowait(event)
        except queue.Full:  # the sampler is behind: the manager's events must not wait
            self._count("events_dropped")

    # --- the sampler thread -----------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / self.config.rate
        next_status = time.monotonic()
        while not self._stop.wait(period):
            try:
                self._sample()
                if time.monotonic() >= next_status:
                    next_status = time.monotonic() + self.config.status_period
                    if self._watched(messages.STATUS):  # the report is the costly one
                        self._publish(messages.STATUS, self._status())
            except Exception as exc:  # noqa: BLE001 - counted; the view goes on
                self._count("errors")
                if self.counters["errors"] in (1, 10, 100, 1000):
                    log.warning("foxglove: publishing failed (%d so far): %s",
                                self.counters["errors"], exc)

    def _sample(self) -> None:
        while True:
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                break
            if event.kind is EventKind.EMERGENCY_STOP:
                self._cause = event.cause
            self.log_message(_event_text(event),
                             WARNING if event.kind is EventKind.EMERGENCY_STOP else INFO)
        j, m = self._joints, self.manager
        ns = time.time_ns()
        position = j.position.tolist()
        if self._watched(messages.JOINT_STATES):
            self._publish(messages.JOINT_STATES, messages.joint_states(
                ns, j.names, position, j.velocity.tolist(), j.torque.tolist()), ns)
        if self._watched(messages.MANAGER):
            cycles, overruns = self._counts()
            self._publish(messages.MANAGER, messages.manager(
                m.state.name, m.active_controller_name, m.estop_latched, self._cause, cycles,
                overruns, self.info()), ns)
        if self.robot is not None:
            if self._subscriptions.description_wanted.is_set():
                self._subscriptions.description_wanted.clear()
                self._publish(messages.ROBOT_DESCRIPTION,
                              messages.robot_description(self.robot.text), ns)
            if self._watched(messages.TRANSFORMS):
                self._publish(messages.TRANSFORMS, messages.frame_transforms(
                    ns, self.robot.transforms(dict(zip(j.names, position)))), ns)

    def _watched(self, channel: Channel) -> bool:
        """Some viewer subscribes to it: a message nobody gets is not built (the view
        shares the loop's interpreter)."""
        return bool(self._channels[channel.topic].has_sinks())

    def _publish(self, channel: Channel, message: dict[str, Any], ns: int | None = None
                 ) -> None:
        self._channels[channel.topic].log(message, log_time=ns or time.time_ns())
        self._count("published")

    def log_message(self, text: str, level: int = INFO) -> None:
        """A line in Foxglove's Log panel (any thread)."""
        if self._watched(messages.LOG):
            ns = time.time_ns()
            self._publish(messages.LOG, messages.log(ns, text, level), ns)

    # --- services (the SDK's threads) -----------------------------------------------------
    def _handler(self, service: str) -> Callable[[Any], bytes]:
        def handle(request: Any) -> bytes:
            self._count("calls")
            try:
                answer = (self._switch(request.payload) if service == "switch"
                          else serve(self.manager, service, self._transport, self._running,
                                     self._recover))
            except Exception as exc:  # noqa: BLE001 - a call must get an answer
                self._count("errors")
                answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            refused = answer.get("ok") is False or answer.get("result") in ("ERROR",
                                                                             "NOT_FOUND")
            if refused:
                self._count("refused")
            self.log_message(f"{service} from Foxglove: "
                             + (f"refused: {answer.get('error', '')}" if refused else "done"),
                             WARNING if refused else INFO)
            return json.dumps(answer).encode()
        return handle

    def _switch(self, payload: bytes) -> dict[str, Any]:
        """``{"controller": NAME}`` (or the bare name) -> the switch's result."""
        try:
            request = json.loads(payload) if payload.strip() else {}
        except (UnicodeDecodeError, json.JSONDecodeError):
            request = None
        raw = (str(request.get("controller", "")).encode() if isinstance(request, dict)
               else payload)
        name, refusal = switch_target(self.manager, raw, self._transport, self._running)
        if name is None:
            return refusal
        future = self.manager.request_switch(name)
        try:
            result = future.result(SWITCH_WAIT)
        except FutureTimeout:
            return {"result": "PENDING", "error": f"no result in {SWITCH_WAIT:g} s"}
        return {"result": result.name,
                **({"error": self.manager.last_refusal} if result.name == "ERROR" else {})}


def _event_text(event: ManagerEvent) -> str:
    if event.kind is EventKind.EMERGENCY_STOP:
        return f"e-stop ({event.state.name}): {event.cause or 'no cause given'}"
    if event.kind is EventKind.ACTIVE_CONTROLLER_CHANGED:
        return f"switched to {event.active_controller} ({event.state.name})"
    return f"state {event.state.name}, controller {event.active_controller}" + (
        f": {event.cause}" if event.cause else "")


def describe(view: FoxgloveView) -> str:
    """The line ``run`` prints: where to connect, what is served, the layout's file."""
    return (f"Foxglove live view on ws://{view.config.host}:{view.port} "
            f"({', '.join(view.topics)}; switch/clear/recover "
            f"{'allowed' if view.config.allow_commands else 'refused'}); layout to import "
            f"in Foxglove: {LAYOUT}")
