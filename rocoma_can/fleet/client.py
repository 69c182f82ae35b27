"""Talking to managers over Zenoh (bridge.py serves them): the client that the CLI verbs'
``--zenoh`` path and ``rocoma-can fleet`` use (cli/fleet.py). A query that nobody answers
is retried until its timeout (a new peer session finds the others within a moment), then
NoAnswer."""
from __future__ import annotations

import json
import time
from typing import Any

from ..errors import NoAnswer, RocomaError
from ..remote import STOPS
from .bridge import FleetError, close_session, open_session
from .config import default_prefix, key_problem

#: one round of a query; repeated until the caller's timeout
ROUND = 0.5


class FleetClient:
    """A Zenoh session that queries one manager's prefix (or lists them all)."""

    def __init__(self, prefix: str = "", connect: list[str] | None = None,
                 mode: str | None = None, multicast: bool | None = None,
                 timeout: float = 3.0) -> None:
        prefix = prefix or default_prefix()
        why = key_problem(prefix)
        if why:
            raise FleetError(f"--zenoh: {why}")
        self.prefix = prefix
        self.timeout = timeout
        self.session = open_session(mode, connect or [], [], multicast)

    def close(self) -> None:
        close_session(self.session)

    def __enter__(self) -> FleetClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def query(self, service: str, payload: str | None = None,
              timeout: float | None = None) -> dict[str, Any]:
        """The manager's answer to ``<prefix>/<service>`` (decoded JSON), within ``timeout``.

        A status query, an e-stop and a failproof stop are sent in rounds until answered
        (asking twice does no harm; an e-stop never waits behind anything). Any other is
        sent once, after a status query has shown the manager reachable: a switch answers
        when it is done and must not be sent twice."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        if service == "status" or service in STOPS:
            while True:
                started = time.monotonic()
                answer = self._get(service, payload, min(ROUND, deadline - started))
                if answer is not None:
                    return answer
                if time.monotonic() >= deadline:
                    raise self._silent(service)
                # nobody matched yet (a session just opened): no query storm meanwhile
                time.sleep(max(0.0, min(ROUND - (time.monotonic() - started),
                                        deadline - time.monotonic())))
        self.query("status", timeout=deadline - time.monotonic())
        answer = self._get(service, payload, deadline - time.monotonic())
        if answer is None:
            raise self._silent(service)
        return answer

    def _get(self, service: str, payload: str | None, timeout: float) -> dict[str, Any] | None:
        key = f"{self.prefix}/{service}"
        for reply in self.session.get(key, payload=payload, timeout=max(0.05, timeout)):
            if reply.ok is None:
                error = reply.err.payload.to_bytes().decode("utf-8", "replace")
                if error == "Timeout":  # Zenoh's own: no answer within the timeout
                    return None
                raise RocomaError(f"{key}: {_shown(error)}")
            return _answer(key, service, reply.ok.payload.to_bytes())
        return None

    def _silent(self, service: str) -> NoAnswer:
        return NoAnswer(f"no answer on Zenoh key {self.prefix}/{service} (is the manager "
                        "running with a zenoh: section, and reachable: --zenoh-connect?)")

    def status(self) -> dict[str, Any]:
        return self.query("status")

    def alive(self, timeout: float | None = None) -> list[str]:
        """The prefixes of every manager whose loop runs (their liveliness tokens)."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        found: set[str] = set()
        while time.monotonic() < deadline:  # all of the time: managers found later count
            started = time.monotonic()
            for reply in self.session.liveliness().get("**/alive", timeout=ROUND):
                if reply.ok is not None:
                    found.add(str(reply.ok.key_expr).removesuffix("/alive"))
            time.sleep(max(0.0, min(ROUND - (time.monotonic() - started),
                                    deadline - time.monotonic())))
        return sorted(found)


#: what each answer must hold, the fields a caller reads (bridge.py's documented shapes)
_SHAPES = {"status": ("state", str), "switch": ("result", str)}


def _answer(key: str, service: str, raw: bytes) -> dict[str, Any]:
    """A manager's answer as its documented shape; anything else on the key (another
    program, a different version) is a RocomaError in one line, never a traceback."""
    try:
        answer = json.loads(raw)
    except ValueError:  # UnicodeDecodeError included: not JSON text
        raise RocomaError(f"{key}: not a rocoma-can manager's answer: "
                          f"{_shown(raw)}") from None
    field, kind = _SHAPES.get(service, ("ok", bool))
    if not isinstance(answer, dict):
        raise RocomaError(f"{key}: not a rocoma-can manager's answer: {_shown(answer)}")
    if service == "status" and "state" not in answer:
        raise RocomaError(f"{key}: the manager could not report: "
                          f"{_shown(answer.get('error', answer))}")
    if not isinstance(answer.get(field), kind):
        raise RocomaError(f"{key}: not a rocoma-can manager's answer (no {field!r}): "
                          f"{_shown(answer)}")
    if "error" in answer and not isinstance(answer["error"], str):
        answer["error"] = _shown(answer["error"])
    return answer


def _shown(value: object, limit: int = 80) -> str:
    """``value`` for a one-line message, cut: an answer may be megabytes."""
    if isinstance(value, bytes):
        head = repr(value[:limit // 4])
        return head if len(value) <= limit // 4 else f"{head}... ({len(value)} bytes)"
    text = (value if isinstance(value, str) else repr(value)).replace("\n", " ")
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"
