"""The manager's services and notifications on Zenoh: one manager per robot, coordinated
over the network; the control loop never goes over it.

Under a prefix (default ``rocoma/<hostname>``), payloads JSON:

* queryables: ``<prefix>/status`` (what ``rocoma-can status --json`` prints, plus
  ``controllers`` and ``zenoh``); ``<prefix>/switch`` (payload: a controller name) ->
  ``{"result": "SWITCHED" | "RUNNING" | "NOT_FOUND" | "ERROR", "error"?}``;
  ``<prefix>/estop``, ``/failproof``, ``/clear``, ``/recover`` -> ``{"ok", "state", "error"?}``;
* publications: ``<prefix>/state`` on every state or active-controller change and every
  e-stop (``{"kind", "state", "controller", "cause", "time"}``, in order); ``<prefix>/drives``
  every ``drives_period`` s (the status report's drives);
* a liveliness token ``<prefix>/alive`` while the loop runs: it vanishes when the loop stops,
  when its cycles stop coming for ``alive_timeout`` s (a hung loop), and with the process.

Safety: an e-stop and a failproof stop are accepted from anyone, whatever their payload (it
is never read: a stop must not depend on what a querier sends); switch, clear and recover
only with ``allow_commands: true`` (Zenoh's own access control and TLS, in the Zenoh config
file given as ``config_file``, decide who reaches this at all). An optional dead-man: with
``deadman: KEY`` the manager e-stops when that liveliness token (an operator's console)
disappears, once it has been seen. The hard stop path stays local: the failproof layer, the
drives' heartbeat consumers, STO wiring.

Threads: Zenoh's own threads answer queries (each answer is a few attribute reads or a
non-blocking manager call; a switch is answered when its future completes, on the switcher
thread) and call the dead-man; the bridge's thread publishes and watches the loop. None of
it runs in the cycle, and Zenoh down or unreachable only shows in the counters (``zenoh``
in the status report).
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

import yaml

from ..errors import RocomaError
from ..events import ManagerEvent
from ..remote import STOPS, StopAnswers, Transport, serve, switch_target, switch_what, tell
from ..stop_surfaces import ZENOH
from ..user_files import read_regular, yaml_problem
from .config import FleetConfig

if TYPE_CHECKING:
    import zenoh

    from ..manager import ControllerManager, SwitchResult

log = logging.getLogger(__name__)

SERVICES = ("status", "switch", "estop", "failproof", "clear", "recover")
class FleetError(RocomaError):
    """Zenoh cannot be used as configured (not installed, an endpoint refused)."""


#: the longest Zenoh config file read, bytes (one is a few kB)
MAX_CONFIG_BYTES = 1 << 20


def _config_from(zenoh: Any, path: str) -> Any:
    """A Zenoh config from a JSON5 or YAML file, read here rather than by Zenoh: its reader
    waits in native code, holding the interpreter, on a FIFO named by mistake
    (user_files.py); OSError or a parse error, said by the caller."""
    try:
        raw = read_regular(path, MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ValueError(f"{path}: {exc.strerror or exc}") from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ValueError(f"{path}: larger than {MAX_CONFIG_BYTES} bytes")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") \
            from None
    if path.endswith((".yaml", ".yml")):
        try:
            text = json.dumps(yaml.safe_load(text))
        except yaml.YAMLError as exc:
            raise ValueError(yaml_problem(exc, path, text)) from None
    return zenoh.Config.from_json5(text)


def open_session(mode: str | None, connect: list[str], listen: list[str],
                 multicast: bool | None, config_file: str | None = None) -> zenoh.Session:
    """A Zenoh session; FleetError says what failed (not installed, an endpoint). ``mode``
    and ``multicast`` None: as the config file (or Zenoh's default) says."""
    try:
        import zenoh
    except ImportError:
        raise FleetError("Zenoh needs eclipse-zenoh: pip install 'rocoma-can[zenoh]'") \
            from None
    try:
        conf = _config_from(zenoh, config_file) if config_file else zenoh.Config()
        if mode is not None:
            conf.insert_json5("mode", json.dumps(mode))
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(connect))
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
        if multicast is not None:
            conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
        return zenoh.open(conf)
    except Exception as exc:  # zenoh.ZError and its config errors: said, never a traceback
        raise FleetError(f"Zenoh session ({_where(mode, connect, listen, config_file)}) "
                         f"could not be opened: {_said(exc)}") from None


def _where(mode: str | None, connect: list[str], listen: list[str],
           config_file: str | None) -> str:
    parts = [mode or "mode as configured"]
    parts += [f"{k} {', '.join(v)}" for k, v in (("connect", connect), ("listen", listen)) if v]
    if config_file:
        parts.append(f"config {config_file}")
    return "; ".join(parts)


def _said(exc: BaseException) -> str:
    """Zenoh's message without the Rust source location it ends with."""
    return str(exc).split(" at /")[0].strip()


class FleetBridge:
    """Serves one manager on Zenoh (see the module). ``status``: what ``rocoma-can status
    --json`` prints (any thread); ``recover``: starts a drive recovery; ``cycles``: the
    loop's cycle count."""

    def __init__(self, config: FleetConfig, manager: ControllerManager,
                 status: Callable[[], dict[str, Any]],
                 recover: Callable[[], Future[bool]] | None = None,
                 cycles: Callable[[], int] = lambda: 0) -> None:
        self.config = config
        self.manager = manager
        self._status = status
        self._recover = recover
        self._cycles = cycles
        self.counters = {"queries": 0, "refused": 0, "published": 0, "errors": 0}
        self._count_lock = threading.Lock()  # Zenoh answers on several threads
        self.deadman_seen = False
        self.session = open_session(config.mode, config.connect, config.listen,
                                    config.multicast, config.config_file)
        self._events: queue.SimpleQueue[ManagerEvent | None] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._running = False
        self._stops = StopAnswers(manager, "zenoh")
        self._token: Any = None
        self._declared: list[Any] = []
        self._unsubscribe: Callable[[], None] | None = None
        self._thread = threading.Thread(target=self._run, name="zenoh-bridge", daemon=True)
        try:
            p = config.prefix
            for service in SERVICES:
                self._declared.append(self.session.declare_queryable(
                    f"{p}/{service}", self._answerer(service)))
            self._state = self.session.declare_publisher(f"{p}/state")
            self._drives = self.session.declare_publisher(f"{p}/drives")
            if config.deadman:
                self._declared.append(self.session.liveliness().declare_subscriber(
                    config.deadman, self._on_deadman, history=True))
        except Exception as exc:  # zenoh.ZError: a key Zenoh refuses, a session gone
            close_session(self.session)
            raise FleetError(f"Zenoh: serving {config.prefix} failed: {_said(exc)}") from None

    # --- life cycle ---------------------------------------------------------------------------
    def start(self) -> FleetBridge:
        """Publish events and watch the loop (the token appears with the first cycles)."""
        self._unsubscribe = self.manager.subscribe(self._events.put)
        self._running = True
        self._thread.start()
        return self

    def loop_stopped(self) -> None:
        """The loop has ended: the token goes at once, not after ``alive_timeout``."""
        self._running = False
        self._events.put(None)

    def close(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._running = False
        self._stop.set()
        self._events.put(None)
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._withdraw()
        for declared in self._declared:
            try:
                declared.undeclare()
            except Exception:  # noqa: BLE001 - a session already gone
                pass
        try:
            close_session(self.session)
        except Exception as exc:  # noqa: BLE001 - the rest of the shutdown must go on
            log.warning("zenoh: closing the session failed: %s", exc)

    def _count(self, what: str) -> None:
        with self._count_lock:
            self.counters[what] += 1

    def info(self) -> dict[str, Any]:
        """What the status report shows of the bridge."""
        return {"prefix": self.config.prefix, "alive": self._token is not None,
                "allow_commands": self.config.allow_commands, "deadman": self.config.deadman,
                **self.counters}

    # --- the bridge thread: publications and the liveliness token -----------------------------
    def _run(self) -> None:
        seen, progress = -1, time.monotonic()
        next_drives = time.monotonic()
        while not self._stop.is_set():
            try:
                event = self._events.get(timeout=0.05)
            except queue.Empty:
                event = None
            if event is not None:
                self._put(self._state, _event_message(event))
            now = time.monotonic()
            cycles = self._cycles()
            if cycles != seen:
                seen, progress = cycles, now
            if self._running and now - progress < self.config.alive_timeout and cycles > 0:
                self._declare()
            else:
                self._withdraw()
            if now >= next_drives:
                next_drives = now + self.config.drives_period
                try:
                    drives = self._status().get("drives", [])
                except Exception:  # noqa: BLE001 - a report that failed: counted
                    self._count("errors")
                    continue
                self._put(self._drives, {"drives": drives})

    def _put(self, publisher: Any, message: dict[str, Any]) -> None:
        try:
            publisher.put(json.dumps(message))
            self._count("published")
        except Exception as exc:  # noqa: BLE001 - Zenoh down: counted, the manager runs on
            self._count("errors")
            if self.counters["errors"] in (1, 10, 100, 1000):
                log.warning("zenoh: publication failed (%d so far): %s",
                            self.counters["errors"], exc)

    def _declare(self) -> None:
        if self._token is None:
            try:
                self._token = self.session.liveliness().declare_token(
                    f"{self.config.prefix}/alive")
            except Exception:  # noqa: BLE001 - tried again next time round
                self._count("errors")

    def _withdraw(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            try:
                token.undeclare()
            except Exception:  # noqa: BLE001 - a session already gone
                pass

    # --- queries (Zenoh's threads) ---------------------------------------------------------
    def _answerer(self, service: str) -> Callable[[Any], None]:
        def answer(query: Any) -> None:
            self._count("queries")
            key = f"{self.config.prefix}/{service}"
            if service == "switch":
                try:
                    self._switch(query, key)
                except Exception as exc:  # noqa: BLE001 - a query must get an answer
                    self._count("errors")
                    self._reply(query, key, {"result": "ERROR",
                                             "error": f"{type(exc).__name__}: {exc}"})
                return
            # Only switch reads its payload: a stop acts whatever it carries (bytes, nothing,
            # megabytes), and status, clear and recover take none.
            if service in STOPS:  # at once; answered when the loop has acted on it
                self._stops.answer(service, self._transport(), self._running,
                                   lambda reply: self._reply(query, key, reply))
                return
            try:
                reply = self._serve(service)
            except Exception as exc:  # noqa: BLE001 - a query must get an answer
                self._count("errors")
                reply = {"ok": False, "state": self.manager.state.name,
                         "error": f"{type(exc).__name__}: {exc}"}
            if reply.get("ok") is False:
                self._count("refused")
            self._reply(query, key, reply)
        return answer

    def _reply(self, query: Any, key: str, answer: dict[str, Any]) -> None:
        """Answer on Zenoh's thread; a querier gone or a session closing is counted, never
        raised into Zenoh (the stop it asked for has happened already)."""
        try:
            _respond(query, key, answer)
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError: the querier went away
            self._count("errors")
            log.debug("zenoh: answering %s failed: %s", key, exc)

    def _serve(self, service: str) -> dict[str, Any]:
        if service == "status":
            return self.status()
        return serve(self.manager, service, self._transport(), self._running, self._recover)

    def _transport(self) -> Transport:
        return Transport(ZENOH, "zenoh.allow_commands", self.config.allow_commands)

    def _switch(self, query: Any, key: str) -> None:
        m = self.manager

        raw = query.payload.to_bytes() if query.payload is not None else b""

        def reply(result: str, error: str = "") -> None:
            if result == "ERROR" or result == "NOT_FOUND":
                self._count("refused")
            answer = {"result": result, **({"error": error} if error else {})}
            tell(m, self._transport(), switch_what(raw), answer)
            self._reply(query, key, answer)
        name, refusal = switch_target(m, raw, self._transport(), self._running)
        if name is None:
            reply(refusal["result"], refusal["error"])
            return

        def done(future: Future[SwitchResult]) -> None:
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - answered, not raised in the switcher
                reply("ERROR", f"{type(exc).__name__}: {exc}")
                return
            reply(result.name, m.last_refusal if result.name == "ERROR" else "")
        m.request_switch(name).add_done_callback(done)

    def status(self) -> dict[str, Any]:
        """The status query's answer: ``rocoma-can status --json``'s document, with the
        switchable controllers and the bridge's own counters."""
        return {**self._status(), "controllers": self.manager.available_controllers(),
                "zenoh": self.info()}

    # --- the dead-man (Zenoh's thread) --------------------------------------------------------
    def _on_deadman(self, sample: Any) -> None:
        import zenoh
        if sample.kind == zenoh.SampleKind.PUT:
            self.deadman_seen = True
        elif self.deadman_seen:
            self.deadman_seen = False
            self.manager.emergency_stop(cause=f"Zenoh dead-man: {sample.key_expr} vanished")


def _respond(query: Any, key: str, answer: dict[str, Any]) -> None:
    """Reply, then finalize the query at once: the querier's default consolidation holds
    replies back until then (Python would finalize it only when the object is collected)."""
    try:
        query.reply(key, json.dumps(answer))
    finally:
        query.drop()


def close_session(session: zenoh.Session) -> None:
    session.close()  # type: ignore[no-untyped-call]  # zenoh 1.x: unannotated


def _event_message(event: ManagerEvent) -> dict[str, Any]:
    """A trace's event message (record/trace.py) with its wall-clock time."""
    from ..record.trace import event_message  # numpy: not for the CLI verbs' quick start
    return {**event_message(event), "time": time.time() - (time.monotonic() - event.time)}
