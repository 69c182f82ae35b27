"""``run --foxglove``: the manager live in Foxglove, on a Foxglove
WebSocket served by foxglove-sdk (extra ``foxglove``), loopback by default.

Channels: messages.py's, each JSON with its JSON schema. ``/joint_states``,
``/rocoma/manager`` and (with a URDF) ``/tf`` every ``1/rate`` s; ``/rocoma/status`` every
``status_period`` s; ``/rocoma/log`` on every manager event (e-stop, state change, switch)
and every command called here; ``/robot_description`` whenever a viewer subscribes to it
(a WebSocket keeps nothing for a late subscriber, and the 3D panel needs it once).

Services (JSON request and answer, as the Zenoh bridge's, rocoma_can/remote.py):
``/rocoma/switch`` (request: ``{"controller": NAME}``, the JSON string or the number;
``switch_request``), ``/rocoma/estop``, ``/rocoma/failproof``, ``/rocoma/clear``,
``/rocoma/recover``. A stop is obeyed from anyone; switch, clear and recover only with
``allow_commands``.

The server runs in the recording's writer process (server.py; record/recorder.py starts
it), fed by the rows the loop copies into shared memory for the recording anyway: building,
encoding and sending messages never takes the loop's interpreter lock. This module is the
loop's process's side (``FoxgloveView``): it answers the server's service calls on the
manager, and while a viewer subscribes to ``/rocoma/status`` it builds the status report
every ``status_period`` s and sends it over. Each viewer has a bounded outbox in the SDK
(``backlog`` messages; full: messages for it are dropped, never waited for, and counted
as ``viewer_drops``), so a slow or vanished viewer costs the loop nothing.
"""
from __future__ import annotations

import importlib.util
import ipaddress
import json
import logging
import re
import socket
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import RocomaError
from ..remote import (
    NOT_RUNNING,
    STOPS,
    StopAnswers,
    Transport,
    refused,
    serve,
    shown,
    switch_target,
    switch_what,
    tell,
)
from ..stop_surfaces import FOXGLOVE
from . import messages

if TYPE_CHECKING:
    from ..manager import ControllerManager
    from .urdf import Robot

log = logging.getLogger(__name__)

DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8765
#: switch calls waiting for their result at most; more are refused
SWITCH_CALLS = 4
#: how often the status feeder looks whether a viewer wants the report, s
STATUS_IDLE = 0.5
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
    """``HOST:PORT``, ``HOST``, ``:PORT``, ``IPV6`` or ``[IPV6]:PORT`` (an empty host or
    port: the default's); ValueError says what is wrong. A malformed address is refused
    here rather than served somewhere the user did not mean: ``[::1`` is not ``::1``."""
    expected = f"expected HOST:PORT, HOST, :PORT or [IPV6]:PORT, got {text!r}"
    if text.startswith("["):
        host, closed, rest = text[1:].partition("]")
        if not closed:
            raise ValueError(f"{expected}: the '[' has no ']'")
        if rest and not rest.startswith(":"):
            raise ValueError(f"{expected}: after ']' comes ':PORT' or nothing")
        if not _ipv6(host):
            raise ValueError(f"{expected}: {host!r} in brackets is not an IPv6 address")
        port = rest[1:]
    elif text.count(":") > 1:  # a bare IPv6 address, no port
        if not _ipv6(text):
            raise ValueError(f"{expected}: an IPv6 address with a port is written "
                             "[IPV6]:PORT")
        host, port = text, ""
    else:
        host, _, port = text.partition(":")
        if host and not _HOST.fullmatch(host):
            raise ValueError(f"{expected}: {host!r} is not a host name or an IPv4 address")
    if not port:
        return host or DEFAULT_HOST, DEFAULT_PORT
    if not (port.isascii() and port.isdigit() and int(port) <= 65535):
        raise ValueError(f"expected HOST:PORT with a port 0..65535, got {text!r}")
    return host or DEFAULT_HOST, int(port)


#: a host name or an IPv4 address as the resolver takes it (letters, digits, '-', '.', '_')
_HOST = re.compile(r"[A-Za-z0-9_.-]+")


def _ipv6(text: str) -> bool:
    try:
        ipaddress.IPv6Address(text)
    except ValueError:
        return False
    return True


def every_interface(host: str) -> bool:
    """Serving on ``host`` listens on every interface (of IPv4 or IPv6). Decided from the
    addresses the host stands for, resolved as the server's bind resolves it (the system
    resolver), not from its spelling: ``0``, ``0.0``, ``::0``, ``0:0:0:0:0:0:0:0``,
    ``::ffff:0.0.0.0`` and a name that resolves to one of those all mean every interface.
    A host that no longer resolves (the server bound it: a resolver gone meanwhile) is
    said to be one: saying so wrongly costs a line, not saying so a robot in reach."""
    try:
        found = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return True
    for *_, address in found:
        try:
            ip = ipaddress.ip_address(str(address[0]).partition("%")[0])
        except ValueError:  # no IP address: no interface of IPv4 or IPv6
            continue
        mapped = ip.ipv4_mapped if isinstance(ip, ipaddress.IPv6Address) else None
        if ip.is_unspecified or (mapped is not None and mapped.is_unspecified):
            return True
    return False


def switch_request(payload: bytes) -> tuple[bytes, str]:
    """The controller a ``/rocoma/switch`` request names, as remote.switch_target reads it
    (its name or its number, as text), and what is wrong with a request that names none
    ("" when nothing is). Foxglove's Service Call panel sends JSON: a JSON string is the
    name itself (``"pd"``, not a controller named with quotes), a whole number its
    number, ``{"controller": NAME or NUMBER}`` either; text that is not JSON is the bare
    name (``pd``)."""
    try:
        request = json.loads(payload)
    except ValueError:  # not JSON (nor UTF-8 text: switch_target says so)
        return payload, ""
    forms = 'a controller is named by a string, its number, or {"controller": NAME}'
    what = "the request"
    if isinstance(request, dict):
        if "controller" not in request:
            keys = f" (its keys: {shown(', '.join(map(str, request)))})" if request else ""
            return b"", f'the request has no "controller"{keys}; {forms}'
        what, request = 'the request\'s "controller"', request["controller"]
    if isinstance(request, str):
        return request.encode(), ""
    if isinstance(request, int) and not isinstance(request, bool):
        return str(request).encode(), ""
    return b"", f"{what} is {_JSON_KINDS.get(type(request), 'no name')}; {forms}"


#: what a JSON value that names no controller is, by its Python type
_JSON_KINDS: dict[type, str] = {bool: "true or false", type(None): "null",
                                float: "a number that is not whole", list: "an array",
                                dict: "an object"}


class FoxgloveView:
    """The live view in the loop's process (see module). ``status``: what ``rocoma-can
    status --json`` prints; ``robot``: the config's URDF (None: no 3D robot). The
    Recorder hands it the server's messages (``on_reply``) and says where it serves
    (``served``)."""

    def __init__(self, config: FoxgloveConfig, manager: ControllerManager,
                 status: Callable[[], dict[str, Any]],
                 recover: Callable[[], Future[bool]] | None = None,
                 robot: Robot | None = None) -> None:
        if importlib.util.find_spec("foxglove") is None:
            raise FoxgloveError("--foxglove needs foxglove-sdk: pip install "
                                "'rocoma-can[foxglove]'")
        self.config = config
        self.manager = manager
        self._status = status
        self._recover = recover
        self.robot = robot
        self._transport = Transport(FOXGLOVE, "--foxglove-allow-commands",
                                    config.allow_commands)
        served = messages.MANAGER_CHANNELS + (messages.ROBOT if robot is not None else ())
        self.topics = [c.topic for c in served]
        #: the calls answered here, the status reports built; the server's counters (``published``,
        #: ``viewer_drops``, ...) as it last sent them
        self.counters = {"calls": 0, "refused": 0, "call_errors": 0, "status_reports": 0}
        self.served_counters: dict[str, int] = {}
        self._lock = threading.Lock()  # counters, port, sender: replies, switch, status threads
        self._port: int | None = None
        self._send: Callable[[dict[str, Any]], bool] | None = None
        self._early: list[dict[str, Any]] = []  # answers before served(): sent by it
        self._gone = False
        self._running = False
        self._status_wanted = threading.Event()
        self._stop = threading.Event()
        self._switching = threading.BoundedSemaphore(SWITCH_CALLS)
        self._stops = StopAnswers(manager, "foxglove")
        self._threads: list[threading.Thread] = []
        self._feeder = threading.Thread(target=self._feed_status, name="foxglove-status",
                                        daemon=True)

    def settings(self) -> dict[str, Any]:
        """What the server in the writer process is told."""
        c = self.config
        return {"host": c.host, "port": c.port, "rate": c.rate, "backlog": c.backlog}

    def served(self, port: int, send: Callable[[dict[str, Any]], bool]) -> None:
        """The server listens on ``port``; ``send`` hands it a message (never waits).
        A call it took before this was said is answered now."""
        with self._lock:
            self._port, self._send = port, send
            early, self._early = self._early, []
        for message in early:
            send(message)

    def gone(self) -> None:
        """The server's process is gone: nothing is built or sent for it any more."""
        with self._lock:
            self._gone, self._send = True, None
        self._status_wanted.clear()

    @property
    def port(self) -> int:
        """The port served (``port: 0`` picks a free one)."""
        if self._port is None:
            raise RuntimeError("the live view is not served yet")
        return self._port

    def start(self) -> FoxgloveView:
        self._running = True
        self._feeder.start()
        return self

    def loop_stopped(self) -> None:
        """Commands other than stops are refused from now on."""
        self._running = False

    def close(self) -> None:
        self._running = False
        self._stop.set()
        for thread in [self._feeder, *self._threads]:
            if thread.is_alive():
                thread.join(SWITCH_WAIT + 1.0)

    def info(self) -> dict[str, Any]:
        """What the status report and /rocoma/manager show of the view."""
        with self._lock:
            counts = {**self.served_counters, **self.counters}
        return {"address": f"{self.config.host}:{self._port}",
                "allow_commands": self.config.allow_commands, **counts}

    def _count(self, what: str) -> None:
        with self._lock:
            self.counters[what] += 1

    # --- the server's messages (the Recorder's replies thread) -----------------------------
    def on_reply(self, reply: dict[str, Any]) -> None:
        if "call" in reply:
            self._call(reply)
        elif "view" in reply:
            with self._lock:
                self.served_counters = dict(reply["view"])
        elif "status_wanted" in reply:
            (self._status_wanted.set if reply["status_wanted"]
             else self._status_wanted.clear)()

    def _call(self, reply: dict[str, Any]) -> None:
        """A stop is requested here at once and answered once the loop has acted on it
        (remote.StopAnswers); a clear or a recover is answered here at once; a switch,
        which waits for its result, on a thread of its own (a few at most: the manager
        runs one switch at a time)."""
        number, service = reply["call"], str(reply["service"])
        try:
            payload = bytes.fromhex(str(reply["payload"]))
        except ValueError:
            payload = b""
        if service in STOPS:
            self._stops.answer(service, self._transport, self._running,
                               lambda answer: self._answer(number, lambda: answer))
        elif service != "switch":
            self._answer(number, lambda: serve(self.manager, service, self._transport,
                                               self._running, self._recover))
        elif self._stop.is_set():  # closed: no thread any more
            self._answer(number, lambda: {"result": "ERROR", "error": NOT_RUNNING})
        elif not self._switching.acquire(blocking=False):
            self._answer(number, lambda: {"result": "ERROR", "error": (
                f"{SWITCH_CALLS} switch calls already wait for their result")})
        else:
            thread = threading.Thread(target=self._switch_call, args=(number, payload),
                                      name="foxglove-switch", daemon=True)
            self._threads = [t for t in self._threads if t.is_alive()] + [thread]
            thread.start()

    def _switch_call(self, number: int, payload: bytes) -> None:
        try:
            self._answer(number, lambda: self._switch(payload))
        finally:
            self._switching.release()

    def _answer(self, number: int, work: Callable[[], dict[str, Any]]) -> None:
        self._count("calls")
        try:
            answer = work()
        except Exception as exc:  # noqa: BLE001 - a call must get an answer
            self._count("call_errors")
            answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        if refused(answer):
            self._count("refused")
        message = {"answer": number, "reply": answer}
        with self._lock:
            send = self._send
            if send is None and not self._gone:
                self._early.append(message)
        if send is not None:
            send(message)

    def _switch(self, payload: bytes) -> dict[str, Any]:
        """A switch request (``switch_request``) -> the switch's result, told to the
        audit trail (remote.tell)."""
        raw, wrong = switch_request(payload)
        answer = self._switched(raw, wrong)
        tell(self.manager, self._transport, switch_what(raw), answer)
        return answer

    def _switched(self, raw: bytes, wrong: str) -> dict[str, Any]:
        name, refusal = switch_target(self.manager, raw, self._transport, self._running,
                                      wrong)
        if name is None:
            return refusal
        future = self.manager.request_switch(name)
        try:
            result = future.result(SWITCH_WAIT)
        except FutureTimeout:
            return {"result": "PENDING", "error": f"no result in {SWITCH_WAIT:g} s"}
        return {"result": result.name,
                **({"error": self.manager.last_refusal} if result.name == "ERROR" else {})}

    # --- the status feeder thread: works only while a viewer watches the report -----------
    def _feed_status(self) -> None:
        while not self._stop.is_set():
            if not self._status_wanted.wait(STATUS_IDLE):
                continue
            send = self._send
            if send is not None and not self._gone:
                try:
                    send({"status": self._status(), "time": time.monotonic()})
                    self._count("status_reports")
                except Exception as exc:  # noqa: BLE001 - the view goes on without it
                    self._count("call_errors")
                    log.warning("foxglove: the status report failed: %s", exc)
            self._stop.wait(self.config.status_period)


def describe_view(view: FoxgloveView) -> str:
    """The line ``run`` prints: where to connect, what is served, the layout's file."""
    host = view.config.host
    every = every_interface(host)  # said: whoever reaches the machine reaches the robot
    return (f"Foxglove live view on ws://{f'[{host}]' if ':' in host else host}:{view.port} "
            f"({', '.join(view.topics)}; switch/clear/recover "
            f"{'allowed' if view.config.allow_commands else 'refused'}); layout to import "
            f"in Foxglove: {LAYOUT}"
            + ("; on every interface: whoever reaches this machine can watch the robot and "
               + ("command it" if view.config.allow_commands else "stop it")
               if every else ""))
