"""The Foxglove WebSocket server of the live view (foxglove.py), run in the recording's
writer process (record/writer.py): building and sending messages never takes the loop's
interpreter lock.

It reads what the writer process has anyway: the loop's signal rows (the ring of
record/rings.py: joint states, manager state, active controller, cycle timing), the manager
events, controller names and e-stop latch the loop's process sends through the pipe, and
the status report, which that process builds only while a viewer subscribes to
``/rocoma/status`` (``status_wanted``). Every ``1/rate`` s a sampler thread publishes
``/joint_states``, ``/rocoma/manager`` and (with a URDF) ``/tf`` from the newest row (a row
once; while no new row comes, ``/rocoma/manager`` alone, with the latch and cause as they
are), and a log line per event, each only to channels a viewer subscribes to.

A service call is handed to the loop's process (``call``: it runs it under remote.py's
rules there and answers) and waited for, on the SDK's thread, up to ANSWER_WAIT. Each
viewer has a bounded outbox in the SDK (``backlog`` messages; full: messages for it are
dropped, never waited for, and each time the SDK says so it is counted as
``viewer_drops``).
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING, Any, cast

from ..overrun import overran, waited
from ..record.trace import state_name
from ..remote import COMMANDS, refused
from . import messages
from .foxglove import SWITCH_WAIT
from .front import Front, FrontError
from .messages import INFO, WARNING, Channel

if TYPE_CHECKING:
    from foxglove.websocket import ServerListener

    from ..record.rings import RingReader
    from ..record.trace import RowLayout
    from .urdf import Robot

#: how long a service call waits for the loop's process to answer (a switch there waits up
#: to SWITCH_WAIT for its result)
ANSWER_WAIT = SWITCH_WAIT + 5.0
#: the longest switch request handed to the loop's process, bytes ({"controller": NAME})
MAX_SWITCH_REQUEST = 1024
#: events waiting for the sampler; more are dropped and counted
EVENT_QUEUE = 256
#: how often the counters go to the loop's process at most, s (its status report shows them)
COUNTS_PERIOD = 0.1
#: the SDK's logger for a viewer whose outbox is full: each record is messages dropped
#: for that viewer (the SDK drops, it never waits)
LOSSY_LOGGER = "foxglove.websocket.connected_client.send_lossy"
#: the SDK's logger for a viewer's connection: an ERROR record for every viewer that goes
#: without closing (its tab closed, its machine gone), which is a viewer's right
POLLER_LOGGER = "foxglove.websocket.connected_client.poller"
#: the SDK's logger of sending to a viewer: an ERROR record for every message sent to a
#: viewer after it went, until its reader notices
SENDER_LOGGER = "foxglove.websocket.connected_client"
#: what the SDK's records of a viewer gone without closing say
GONE_SIGNS = ("reset by peer", "without closing handshake", "Broken pipe")


class ServeError(Exception):
    """The server cannot start (the SDK missing, the address taken): its one line."""


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


class _Drops(logging.Handler):
    """Counts the SDK's "outbox for client ... full" records (on its threads)."""

    def __init__(self, count: Callable[[str], None]) -> None:
        super().__init__(logging.INFO)
        self._count = count

    def emit(self, record: logging.LogRecord) -> None:
        if "full" in record.getMessage():
            self._count("viewer_drops")


class _Gone(logging.Filter):
    """Counts a viewer that went without closing (its connection reset, or ended without
    the WebSocket's closing handshake) instead of the SDK's ERROR line on the run's
    terminal, and keeps quiet the SDK's lines about sending to it after it went (one a
    message); any other record passes."""

    def __init__(self, count: Callable[[str], None]) -> None:
        super().__init__()
        self._count = count

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        if not any(sign in text for sign in GONE_SIGNS):
            return True
        if record.name == POLLER_LOGGER:  # the SDK's reader of that viewer: once a viewer
            self._count("viewers_gone")
        return False


class FoxgloveServer:
    """The live view's server (see module). ``settings``: host, port, rate, backlog (as
    foxglove.FoxgloveConfig); ``period``: the loop's, for overruns; ``call(service,
    payload)`` hands a service call to the loop's process and returns the Future of its
    answer; ``report(message)`` tells that process something (counters, status wanted);
    ``noted(text, level)``: each service call's log line, for the recordings."""

    def __init__(self, settings: Mapping[str, Any], rows: RingReader, layout: RowLayout,
                 period: float, robot: Robot | None,
                 call: Callable[[str, bytes], Future[dict[str, Any]]],
                 report: Callable[[dict[str, Any]], None],
                 noted: Callable[[str, int], None] | None = None) -> None:
        try:
            import foxglove
            from foxglove.websocket import Capability
        except ImportError as exc:
            raise ServeError(f"--foxglove needs foxglove-sdk ({exc}): pip install "
                             "'rocoma-can[foxglove]'") from None
        self._rows, self._layout, self._period = rows, layout, period
        self._rate = float(settings["rate"])
        self.robot = robot
        self._call, self._report, self._noted = call, report, noted
        self.controllers: dict[int, str] = {}
        self.latched = False
        self._cause = ""
        self._seen = -1          # the next row's number the sampler has not read
        self._last: list[float] | None = None  # the newest row read
        self._cycles = self._overruns = self._waiting = 0
        self.counters = {"published": 0, "events_dropped": 0, "viewer_drops": 0,
                         "viewers_gone": 0, "viewers_refused": 0, "viewers_stalled": 0,
                         "errors": 0}
        self._reported: dict[str, int] = {}
        self._status_wanted = False
        self._count_lock = threading.Lock()  # the SDK's threads count too
        self._events: queue.Queue[dict[str, Any]] = queue.Queue(EVENT_QUEUE)
        self._status: queue.Queue[dict[str, Any]] = queue.Queue(1)
        self._stop = threading.Event()
        self._context = foxglove.Context()
        served = messages.MANAGER_CHANNELS + (messages.ROBOT if robot is not None else ())
        self._channels = {c.topic: foxglove.Channel(c.topic, schema=c.schema,
                                                    context=self._context) for c in served}
        self._subscriptions = _Subscriptions()
        # the SDK says of a viewer's full outbox at INFO: heard here whatever the log level
        self._drops = _Drops(self._count)
        lossy = logging.getLogger(LOSSY_LOGGER)
        lossy.addHandler(self._drops)
        lossy.setLevel(logging.INFO)
        self._gone = _Gone(self._count)
        for name in (POLLER_LOGGER, SENDER_LOGGER):
            logging.getLogger(name).addFilter(self._gone)
        def schema(doc: dict[str, Any]) -> Any:
            return foxglove.MessageSchema(encoding="json", schema=foxglove.Schema(
                name=str(doc["title"]), encoding="jsonschema", data=json.dumps(doc).encode()))
        services = [foxglove.Service(f"/rocoma/{name}", schema=foxglove.ServiceSchema(
            f"rocoma.{name}", request=schema(messages.SERVICES[name][0]),
            response=schema(messages.SERVICES[name][1])), handler=self._handler(name))
            for name in COMMANDS]
        host, port = str(settings["host"]), int(settings["port"])
        try:  # the SDK on a loopback port of its own; viewers reach it through the front
            self.server = foxglove.start_server(
                name="rocoma-can", host="127.0.0.1", port=0,
                capabilities=[Capability.Services], supported_encodings=["json"],
                services=services, context=self._context,
                server_listener=cast("ServerListener", self._subscriptions),
                message_backlog_size=int(settings["backlog"]))
        except Exception as exc:  # the SDK's RuntimeError
            self._unhook()
            raise ServeError(f"Foxglove: cannot serve: {exc}") from None
        try:
            self._front = Front(host, port, int(self.server.port), self._count)
        except FrontError as exc:  # the address taken or unknown
            self.server.stop()
            self._unhook()
            raise ServeError(f"Foxglove: {exc}") from None
        self._thread = threading.Thread(target=self._run, name="foxglove-view", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The port served (``port: 0`` picks a free one)."""
        return int(self._front.port)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.server.stop()
        self._front.close()
        self._unhook()

    def _unhook(self) -> None:
        logging.getLogger(LOSSY_LOGGER).removeHandler(self._drops)
        for name in (POLLER_LOGGER, SENDER_LOGGER):
            logging.getLogger(name).removeFilter(self._gone)

    # --- what the loop's process sends (the writer's command thread) -----------------------
    def on_event(self, event: dict[str, Any]) -> None:
        """A manager event (trace.event_message): a log line and the e-stop's cause."""
        try:
            self._events.put_nowait(event)
        except queue.Full:  # the sampler is behind
            self._count("events_dropped")

    def on_status(self, report: dict[str, Any]) -> None:
        """The status report, published by the sampler (only the newest waits)."""
        try:
            self._status.get_nowait()
        except queue.Empty:
            pass
        self._status.put_nowait(report)

    # --- the sampler thread -----------------------------------------------------------------
    def _run(self) -> None:
        period, next_counts = 1.0 / self._rate, 0.0
        while not self._stop.wait(period):
            try:
                self._sample()
            except Exception as exc:  # noqa: BLE001 - counted and said; the view goes on
                self._count("errors")
                if self.counters["errors"] in (1, 10, 100, 1000):
                    logging.getLogger(__name__).warning(
                        "foxglove: publishing failed (%d so far): %s",
                        self.counters["errors"], exc)
            wanted = self._watched(messages.STATUS)
            if wanted != self._status_wanted:
                self._status_wanted = wanted
                self._report({"status_wanted": wanted})
            now = time.monotonic()
            if now >= next_counts:
                next_counts = now + COUNTS_PERIOD
                with self._count_lock:
                    counts = dict(self.counters)
                if counts != self._reported:
                    self._reported = counts
                    self._report({"view": counts})

    def _sample(self) -> None:
        while True:
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                break
            if event["kind"] == "emergency_stop":
                self._cause = event["cause"]
            self.log_message(*messages.event_log(event))
        try:
            self._publish(messages.STATUS, self._status.get_nowait())
        except queue.Empty:
            pass
        if self._seen < 0:  # the first sample: the newest row
            self._seen = max(self._rows.count() - 1, 0)
        first, rows = self._rows.read(self._seen)
        fresh = bool(len(rows))
        if fresh:
            self._cycles = self._seen = first + len(rows)
            over = overran(rows[:, 2], rows[:, 3], self._period)
            self._overruns += int(over.sum())
            self._waiting += int((over & waited(rows[:, 2], rows[:, 3], rows[:, 6])).sum())
            self._last = rows[-1].tolist()
        values = self._last
        if values is None:  # no cycle yet: nothing known to show
            return
        # a row's stamp is the loop's monotonic clock (one clock for every process); with
        # no new row (the loop not cycling: bring-up, after its stop) the manager's
        # message goes on, stamped now, for the latch and the cause it carries
        ns = (int((values[0] + time.time() - time.monotonic()) * 1e9) if fresh
              else time.time_ns())
        layout = self._layout
        position, velocity, torque = (values[s] for s in layout.slices[:3])
        if fresh and self._watched(messages.JOINT_STATES):
            self._publish(messages.JOINT_STATES, messages.joint_states(
                ns, layout.names, position, velocity, torque), ns)
        if self._watched(messages.MANAGER):
            with self._count_lock:
                counts = dict(self.counters)
            self._publish(messages.MANAGER, messages.manager(
                state_name(values[4]), self.controllers.get(int(values[5]), ""),
                self.latched, self._cause, self._cycles, (self._overruns, self._waiting),
                counts), ns)
        if self.robot is not None:
            if self._subscriptions.description_wanted.is_set():
                self._subscriptions.description_wanted.clear()
                self._publish(messages.ROBOT_DESCRIPTION,
                              messages.robot_description(self.robot.text), ns)
            if fresh and self._watched(messages.TRANSFORMS):
                self._publish(messages.TRANSFORMS, messages.frame_transforms(
                    ns, self.robot.transforms(dict(zip(layout.names, position)))), ns)

    def _watched(self, channel: Channel) -> bool:
        """Some viewer subscribes to it: a message nobody gets is not built."""
        return bool(self._channels[channel.topic].has_sinks())

    def _publish(self, channel: Channel, message: dict[str, Any], ns: int | None = None
                 ) -> None:
        self._channels[channel.topic].log(message, log_time=ns or time.time_ns())
        self._count("published")

    def _count(self, what: str) -> None:
        with self._count_lock:
            self.counters[what] += 1

    def log_message(self, text: str, level: int = INFO) -> None:
        """A line in Foxglove's Log panel (any thread)."""
        if self._watched(messages.LOG):
            ns = time.time_ns()
            self._publish(messages.LOG, messages.log(ns, text, level), ns)

    # --- services (the SDK's threads) -----------------------------------------------------
    def _handler(self, service: str) -> Callable[[Any], bytes]:
        def handle(request: Any) -> bytes:
            answer = self._ask(service, request.payload)
            no = refused(answer)
            text = f"{service} from Foxglove: " + (
                f"refused: {answer.get('error', '')}" if no else "done")
            level = WARNING if no else INFO
            self.log_message(text, level)
            if self._noted is not None:
                self._noted(text, level)
            return json.dumps(answer).encode()
        return handle

    def _ask(self, service: str, payload: bytes) -> dict[str, Any]:
        """The loop's process's answer to a call. Only a switch's payload is read there
        (a stop must not depend on it); one longer than MAX_SWITCH_REQUEST is refused here,
        never parsed in the loop's interpreter."""
        if service != "switch":
            payload = b""
        elif len(payload) > MAX_SWITCH_REQUEST:
            return {"result": "NOT_FOUND", "error": (
                f"no controller: the request is {len(payload)} bytes, a switch request "
                f"takes at most {MAX_SWITCH_REQUEST}")}
        try:
            future = self._call(service, bytes(payload))
            try:
                return future.result(ANSWER_WAIT)
            except FutureTimeout:
                future.cancel()  # a late answer finds nobody waiting
                return {"ok": False, "error": f"the manager's process did not answer "
                                              f"within {ANSWER_WAIT:g} s"}
        except Exception as exc:  # noqa: BLE001 - a call must get an answer
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
