"""``run --foxglove``: the manager live in Foxglove (or PlotJuggler), on a Foxglove
WebSocket served by foxglove-sdk (extra ``foxglove``), loopback by default.

Channels (JSON, each with its JSON schema):

* ``/joint_states``: ``{"timestamp", "name", "position", "velocity", "effort"}`` per joint,
  in SI units (rad, rad/s, Nm), every ``1/rate`` s;
* ``/rocoma/manager``: state, active controller, e-stop latch and the last stop's cause,
  the loop's cycle and overrun counts, and this server's own counters (drops), at ``rate``;
* ``/rocoma/status``: the status report (``status --json``: cycle statistics, each bus's
  load and errors, the drives) every ``status_period`` s;
* ``/rocoma/log``: a ``foxglove.Log`` on every manager event (e-stop, state change, switch)
  and every command called here.

Services (JSON request and answer, as the Zenoh bridge's, rocoma_can/remote.py):
``/rocoma/switch`` (request: ``{"controller": NAME}``), ``/rocoma/estop``,
``/rocoma/failproof``, ``/rocoma/clear``, ``/rocoma/recover``. A stop is obeyed from anyone;
switch, clear and recover only with ``allow_commands``.

The loop never publishes: the view's sampler thread copies from the joint state arrays the
loop writes in place (each array whole, under the GIL; position and velocity may come from
neighbouring cycles) and from plain counters, at its own rate. The manager's events reach
it through a bounded queue (full: dropped, counted). Each client has a bounded backlog in
the SDK (``backlog`` messages; full: its oldest message is dropped), so a slow or vanished
viewer costs the loop nothing.
"""
from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from ..errors import RocomaError
from ..events import EventKind, ManagerEvent
from ..remote import COMMANDS, Transport, serve, switch_target

if TYPE_CHECKING:
    from ..manager import ControllerManager

log = logging.getLogger(__name__)

DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8765
#: events waiting for the sampler; more are dropped and counted
EVENT_QUEUE = 256
#: how long a switch service call waits for the switch's result (the switcher's own
#: timeouts end it sooner)
SWITCH_WAIT = 10.0


class FoxgloveError(RocomaError):
    """The live view cannot be served (foxglove-sdk missing, the address taken)."""


@dataclass
class FoxgloveConfig:
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    rate: float = 30.0           # Hz: /joint_states and /rocoma/manager
    status_period: float = 0.5   # s between /rocoma/status messages
    allow_commands: bool = False  # switch, clear, recover from Foxglove
    backlog: int = 256           # messages per client before its oldest are dropped


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


def _numbers(values: Any) -> list[float | None]:
    """JSON has no NaN: a joint without feedback shows as null."""
    return [v if math.isfinite(v) else None for v in values.tolist()]


def _schema(title: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": properties}


_NUMBERS = {"type": "array", "items": {"type": ["number", "null"]}}
_TIMESTAMP = {"type": "object", "properties": {"sec": {"type": "integer"},
                                               "nsec": {"type": "integer"}}}
SCHEMAS = {
    "/joint_states": _schema("rocoma.JointStates", {
        "timestamp": _TIMESTAMP, "name": {"type": "array", "items": {"type": "string"}},
        "position": _NUMBERS, "velocity": _NUMBERS, "effort": _NUMBERS}),
    "/rocoma/manager": _schema("rocoma.Manager", {
        "state": {"type": "string"}, "controller": {"type": "string"},
        "latched": {"type": "boolean"}, "cause": {"type": "string"},
        "cycles": {"type": "integer"}, "overruns": {"type": "integer"},
        "foxglove": {"type": "object"}}),
    "/rocoma/status": _schema("rocoma.Status", {}),
    "/rocoma/log": _schema("foxglove.Log", {
        "timestamp": _TIMESTAMP, "level": {"type": "integer"}, "message": {"type": "string"},
        "name": {"type": "string"}, "file": {"type": "string"}, "line": {"type": "integer"}}),
}
#: foxglove.Log levels
INFO, WARNING, ERROR = 2, 3, 4


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


class FoxgloveView:
    """Serves one manager on a Foxglove WebSocket (see the module). ``status``: what
    ``rocoma-can status --json`` prints; ``counts``: the loop's (cycles, overruns)."""

    def __init__(self, config: FoxgloveConfig, manager: ControllerManager,
                 joints: JointSource, status: Callable[[], dict[str, Any]],
                 counts: Callable[[], tuple[int, int]],
                 recover: Callable[[], Future[bool]] | None = None) -> None:
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
        self._transport = Transport("Foxglove", "--foxglove-allow-commands",
                                    config.allow_commands)
        self.counters = {"published": 0, "events_dropped": 0, "calls": 0, "refused": 0,
                         "errors": 0}
        self._count_lock = threading.Lock()  # service calls come on the SDK's threads
        self._events: queue.Queue[ManagerEvent] = queue.Queue(EVENT_QUEUE)
        self._cause = ""
        self._running = False
        self._stop = threading.Event()
        self._unsubscribe: Callable[[], None] | None = None
        self._context = foxglove.Context()
        self._channels = {topic: foxglove.Channel(topic, schema=schema, context=self._context)
                          for topic, schema in SCHEMAS.items()}
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
                message_backlog_size=config.backlog)
        except Exception as exc:  # the SDK's RuntimeError: the address taken or unknown
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
                    self._publish("/rocoma/status", self._status())
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
        self._publish("/joint_states", {
            "timestamp": _stamp(ns), "name": list(j.names), "position": _numbers(j.position),
            "velocity": _numbers(j.velocity), "effort": _numbers(j.torque)}, ns)
        cycles, overruns = self._counts()
        self._publish("/rocoma/manager", {
            "state": m.state.name, "controller": m.active_controller_name,
            "latched": m.estop_latched, "cause": self._cause, "cycles": cycles,
            "overruns": overruns, "foxglove": self.info()}, ns)

    def _publish(self, topic: str, message: dict[str, Any], ns: int | None = None) -> None:
        self._channels[topic].log(message, log_time=ns or time.time_ns())
        self._count("published")

    def log_message(self, text: str, level: int = INFO) -> None:
        """A line in Foxglove's Log panel (any thread)."""
        ns = time.time_ns()
        self._publish("/rocoma/log", {"timestamp": _stamp(ns), "level": level,
                                      "message": text, "name": "rocoma-can", "file": "",
                                      "line": 0}, ns)

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


def describe(view: FoxgloveView, topics: Sequence[str] = tuple(SCHEMAS)) -> str:
    """The line ``run`` prints: where to connect and what is served."""
    return (f"Foxglove live view on ws://{view.config.host}:{view.port} "
            f"({', '.join(topics)}; switch/clear/recover "
            f"{'allowed' if view.config.allow_commands else 'refused'})")
