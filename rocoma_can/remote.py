"""The manager's commands from a remote caller (the Zenoh bridge, the Foxglove live view):
one set of rules, so no transport can be laxer than another.

A stop (e-stop, failproof) is obeyed from anyone and never reads what the caller sent: a
stop must not depend on a payload. Switch, clear and recover need the transport's
``allow_commands`` and a running loop. Every answer is a JSON-ready dict:
``{"ok", "state", "error"?}`` for the services, ``{"result", "error"?}`` for a switch. A
stop's ``state`` is the one after it: the loop acts on a stop at its next update, and the
answer waits for that, STOP_WAIT at most (``"pending": true`` when it had to go without).
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from .stop_surfaces import StopSurface

if TYPE_CHECKING:
    from .manager import ControllerManager

#: the services anyone may use; the others need ``allow_commands``
STOPS = ("estop", "failproof")
#: every command service (``status`` and the like are each transport's own)
COMMANDS = ("switch", "estop", "failproof", "clear", "recover")
NOT_RUNNING = "the manager's loop is not running"
#: s a stop's answer waits at most for the loop to act on it (two updates: two periods,
#: unless the loop is starved or stalled; then the answer goes, ``pending``)
STOP_WAIT = 1.0
#: s between two looks at the manager's update count meanwhile
STOP_POLL = 0.001
#: stop answers waiting at once per transport (StopAnswers)
STOP_CALLS = 4
#: a switch's controller name is echoed back at most this long: a payload of any size may
#: come in
SHOWN_NAME = 64


@dataclass(frozen=True)
class Transport:
    """Who calls: ``surface`` the stop surface it is (its label in the stop causes and
    refusals: "Zenoh"), ``setting`` the config key that allows commands
    ("zenoh.allow_commands")."""
    surface: StopSurface
    setting: str
    allow_commands: bool

    @property
    def name(self) -> str:
        return self.surface.label

    def not_allowed(self, service: str) -> str:
        return (f"{service} over {self.name} is not allowed by this manager's config "
                f"({self.setting}: false); e-stop and failproof are")


def serve(manager: ControllerManager, service: str, transport: Transport, running: bool,
          recover: Callable[[], Future[bool]] | None) -> dict[str, Any]:
    """Run one of estop, failproof, clear, recover under the rules (see the module); a
    request other than a stop is told to the audit trail with its answer (``tell``)."""
    if service in STOPS:
        return stopped(manager, stop(manager, service, transport), running)
    latched = manager.estop_latched
    answer = _serve(manager, service, transport, running, recover)
    tell(manager, transport, service, answer, cleared(latched) if service == "clear" else "")
    return answer


def cleared(latched: bool) -> str:
    """What a clear did, by whether the latch was set (every surface says it so)."""
    return ("the e-stop latch is cleared" if latched
            else "nothing to clear (the e-stop latch was not set)")


def _serve(manager: ControllerManager, service: str, transport: Transport, running: bool,
           recover: Callable[[], Future[bool]] | None) -> dict[str, Any]:
    m = manager
    if not transport.allow_commands:
        return {"ok": False, "state": m.state.name, "error": transport.not_allowed(service)}
    if not running:
        return {"ok": False, "state": m.state.name, "error": NOT_RUNNING}
    if service == "clear":
        if not m.clear_emergency_stop():
            return {"ok": False, "state": m.state.name,
                    "error": "the e-stop latch was not cleared (see the manager log)"}
    elif service == "recover":
        if recover is None:
            return {"ok": False, "state": m.state.name,
                    "error": "this manager has no drives to recover"}
        recover()
        return {"ok": True, "state": m.state.name, "recovery": "started"}
    else:
        return {"ok": False, "state": m.state.name, "error": f"no service {shown(service)}"}
    return {"ok": True, "state": m.state.name}


def tell(manager: ControllerManager, transport: Transport, what: str,
         answer: dict[str, Any], done: str = "") -> None:
    """A request from ``transport`` and its ``answer`` (a service's or a switch's), told to
    the audit trail (ControllerManager.notify_request); ``done``: what an answer that
    says yes did, when the answer does not say it."""
    error = answer.get("error")
    if "result" in answer:  # a switch
        said = str(answer["result"]) + (f": {error}" if error else "")
    elif answer.get("ok"):
        said = done or ("started" if answer.get("recovery") == "started" else "done")
    else:
        said = f"refused: {error or 'no reason given'}"
    manager.notify_request(f"{transport.name}: {what}: {said}")


def stop(manager: ControllerManager, service: str, transport: Transport) -> int:
    """The stop ``service`` (estop, failproof) requested, at once, through the transport's
    stop surface; the manager's update count just after, for ``stopped``."""
    transport.surface.stop(manager, service)
    return manager.cycle_count


def stopped(manager: ControllerManager, updates: int, running: bool) -> dict[str, Any]:
    """A stop's answer, with the state once the loop has acted on it: ``updates`` was the
    manager's update count just after the request (``stop``); an update increments it as
    it begins and then applies what is queued, so by ``updates + 2`` one that began after
    the request has ended (an e-stop in EMERGENCY goes on to FAILPROOF, one without an
    emergency controller too). Waits up to STOP_WAIT, only while the loop ``running``."""
    deadline = time.monotonic() + (STOP_WAIT if running else 0.0)
    while manager.cycle_count < updates + 2 and time.monotonic() < deadline:
        time.sleep(STOP_POLL)
    applied = manager.cycle_count >= updates + 2
    return {"ok": True, "state": manager.state.name, **({} if applied else {"pending": True})}


class StopAnswers:
    """A transport's stop calls: each stop is requested at once on the caller's thread,
    and its answer (``stopped``) waits on a short-lived thread of its own, STOP_CALLS at
    most at once (more are answered at once, ``pending``): the transport's thread (Zenoh's,
    the recorder's replies) never waits for the loop."""

    def __init__(self, manager: ControllerManager, name: str) -> None:
        self._manager, self._name = manager, name
        self._slots = threading.BoundedSemaphore(STOP_CALLS)

    def answer(self, service: str, transport: Transport, running: bool,
               reply: Callable[[dict[str, Any]], None]) -> None:
        m = self._manager
        updates = stop(m, service, transport)
        if not self._slots.acquire(blocking=False):
            reply(stopped(m, updates, running=False))
            return

        def wait() -> None:
            try:
                reply(stopped(m, updates, running))
            finally:
                self._slots.release()
        try:
            threading.Thread(target=wait, name=f"{self._name}-stop", daemon=True).start()
        except RuntimeError:  # no thread to be had: the stop stands, answered at once
            self._slots.release()
            reply(stopped(m, updates, running=False))


def switch_target(manager: ControllerManager, raw: bytes, transport: Transport,
                  running: bool, wrong: str = "") -> tuple[str | None, dict[str, Any]]:
    """The controller a switch request names (a name, or its number in ``list``) and None,
    or None and the refusal to answer with. ``wrong``: why the request names no controller
    at all (a transport's own request format), said only after the rules' refusals, as an
    unknown name is: a caller not allowed to switch learns nothing of the controllers."""
    def refused(result: str, error: str) -> tuple[None, dict[str, Any]]:
        return None, {"result": result, "error": error}
    if not transport.allow_commands:
        return refused("ERROR", transport.not_allowed("switch"))
    if not running:
        return refused("ERROR", NOT_RUNNING)
    names = manager.available_controllers()
    if wrong:
        return refused("NOT_FOUND", f"no controller: {wrong} (controllers: {', '.join(names)})")
    try:
        name = raw.decode("utf-8").strip()
    except UnicodeDecodeError:  # names none of ours; said without echoing the bytes
        return refused("NOT_FOUND", f"no controller: the payload is {len(raw)} bytes that "
                                    f"are not UTF-8 text (controllers: {', '.join(names)})")
    # a number from `list` (ASCII digits, short: int() of "²" or 5000 digits raises)
    if name.isascii() and name.isdigit() and len(name) <= 6 and 1 <= int(name) <= len(names):
        name = names[int(name) - 1]
    if name not in names:
        return refused("NOT_FOUND", f"no controller {shown(name)} (controllers: "
                                    f"{', '.join(names)})")
    blocked = manager.switch_blocked()
    if blocked is not None:
        return refused("ERROR", f"switch refused: {blocked}")
    return name, {}


def switch_what(raw: bytes) -> str:
    """A switch request as the audit trail names it: "switch to 'pd'" (cut as answers cut
    it: a payload of any size may come in)."""
    try:
        return f"switch to {shown(raw.decode('utf-8').strip())}"
    except UnicodeDecodeError:
        return f"switch ({len(raw)} bytes, not UTF-8 text)"


def refused(answer: dict[str, Any]) -> bool:
    """A command's answer says no (a service's ``ok`` false, a switch's ERROR or
    NOT_FOUND)."""
    return answer.get("ok") is False or answer.get("result") in ("ERROR", "NOT_FOUND")


def shown(name: str) -> str:
    """``name`` quoted for an answer, cut to SHOWN_NAME characters with its length."""
    if len(name) <= SHOWN_NAME:
        return repr(name)
    return f"{name[:SHOWN_NAME]!r}... ({len(name)} characters)"
