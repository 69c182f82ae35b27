"""The recording's writer process (``python -m rocoma_can.record.writer``; recorder.py
starts it): every slow part of recording and of the live view, on an interpreter of its
own.

The loop's process hands over through shared memory (rings.py: signal rows, each bus's
received and sent frames) and a pipe (this process's stdin, one JSON object a line): first
the set-up (``Spec``), then manager events ``{"event": ...}`` (each with the e-stop latch it
left: the files' latch, live_channels.EstopHistory), controller numbers ``{"controllers":
{name: number}}``, the e-stop latch ``{"latched": bool}`` (as the loop's process sees it
change: the live view's), for the live view the answer to a service call ``{"answer": id,
"reply": {...}}``, the status report ``{"status": {...}, "time": t}`` (for the view, and
into the files' /rocoma/status), and ``{"close": true}``. Every ``POLL`` s it writes what
the rings got (``--record``: recording.py) and the flight records due (flight.py), yielding
its CPU every 0.2 ms of that work (pacing.py: a loop queued on its CPU waits for one piece,
not a writing burst); the live view (live/server.py) publishes on its own threads. It
answers on stdout, one JSON object a line: ``{"ready": true, "foxglove_port": port}`` or
``{"failed": reason, "of": ...}`` at start, ``{"flight_record": path, "cause": ...}``,
``{"error": reason, "of": "recording" | "flight"}``, the live view's ``{"call": id,
"service": name, "payload": hex}``, ``{"view": counters}`` and ``{"status_wanted": bool}``,
and last ``{"closed": true}``.
Answers, the status report and the live view's events are taken as they come in (the
commands' thread), not after a long write.

It ignores SIGTERM and SIGINT (the loop's process closes it). Its stdin ending without
``close`` means the loop's process died (killed, crashed): what
is in the rings is written, the flight recorder writes a record of the last seconds (cause
"the manager's process ended without closing"), and it ends.
"""
from __future__ import annotations

import itertools
import json
import logging
import math
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Mapping
from concurrent.futures import Future, InvalidStateError
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

from ..live.server import FoxgloveServer, ServeError
from ..live.urdf import Robot
from ..log_format import ConsoleFormatter
from .can_log import RecordingError
from .flight import FlightRecords
from .live_channels import Facts, LiveChannels
from .pacing import Pacer
from .recording import Recording
from .rings import RingReader, RingSpec, SharedFile
from .trace import McapWriter, RowLayout

log = logging.getLogger("rocoma_can.record.writer")  # (run as __main__: -m)

#: how often the rings are written out, s
POLL = 0.05
#: how long a frame stays out of its bus's log at least, s (recording.BusLog): frames
#: reach the rings up to a cycle late (two at a low rate) or as late as the bus's reader;
#: and a row out of the trace, for its cycle's events to come through the pipe
HOLD = 0.25


@dataclass
class Spec:
    """What the writer is told at start: the shared file and its rings (``rows``; per bus
    label, its channel and its received and sent rings), the joints, and what to write."""
    fd: int
    size: int
    rows: RingSpec
    buses: dict[str, tuple[str, list[RingSpec]]]
    joints: list[str]
    controllers: dict[str, int]
    record: str | None = None
    flight: str | None = None
    seconds: float = 10.0
    rate: float = 100.0
    robot: dict[str, Any] | None = None  # the config's URDF as read (urdf.Robot.as_json)
    foxglove: dict[str, Any] | None = None  # the live view's server (host, port, ...)
    loop_cpus: list[int] = field(default_factory=list)  # realtime.cpus: kept off them
    latched: bool = False  # the manager's e-stop latch at start (events say its changes)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> Spec:
        raw = json.loads(text)
        raw["rows"] = RingSpec(**raw["rows"])
        raw["buses"] = {label: (channel, [RingSpec(**r) for r in rings])
                        for label, (channel, rings) in raw["buses"].items()}
        return cls(**raw)


class Writer:
    """The writer's state: the rings, the recording, the flight records, the live view."""

    def __init__(self, spec: Spec, reply: IO[str]) -> None:
        self._reply, self._gone = reply, False
        self._reply_lock = threading.Lock()  # the live view's threads answer too
        self._calls: dict[int, Future[dict[str, Any]]] = {}
        self._calls_lock = threading.Lock()
        self._calls_closed = False  # the loop's process answers no more
        self._call_ids = itertools.count(1)
        self._files = spec.record is not None or spec.flight is not None
        if self._files:
            _check_mcap()
        self.shared = SharedFile(spec.size, spec.fd)
        layout = RowLayout(spec.joints)
        rows = RingReader(self.shared, spec.rows)
        rings = {label: (channel, [RingReader(self.shared, r) for r in specs])
                 for label, (channel, specs) in spec.buses.items()}
        self.controllers = {number: name for name, number in spec.controllers.items()}
        self.events: list[dict[str, Any]] = []  # for the recording, since its last write
        # (a row older than the rows' ring holds is never read: its e-stops are forgotten)
        self.facts = Facts(window=spec.seconds, latched=spec.latched,
                           span=spec.rows.capacity / spec.rate)
        robot = Robot.from_json(spec.robot) if spec.robot is not None else None
        self.view: FoxgloveServer | None = None
        if spec.foxglove is not None:  # first: an address taken leaves no files behind
            self.view = FoxgloveServer(spec.foxglove, RingReader(self.shared, spec.rows),
                                       layout, 1.0 / spec.rate, robot, self.call,
                                       lambda message: self.say(**message), self._noted)
            self.view.controllers.update(self.controllers)
            self.view.latched = spec.latched

        def live(writer: McapWriter) -> LiveChannels:
            return LiveChannels(writer, layout, 1.0 / spec.rate, robot, self.facts)
        self.pace = Pacer()  # every file's writing gives way to the loop (pacing.py)
        self.recording = (Recording(Path(spec.record), layout, rows, rings, live, self.pace)
                          if spec.record is not None else None)
        self._hold = max(HOLD, 2.0 / spec.rate)
        self.flight = (FlightRecords(Path(spec.flight), spec.seconds, layout, rows,
                                     {label: r for label, (_, r) in rings.items()}, live,
                                     self.pace)
                       if spec.flight is not None else None)

    def _noted(self, text: str, level: int) -> None:
        """A live view's service-call line, for the files' /rocoma/log (the SDK's thread)."""
        if self._files:
            self.facts.logs.add(time.monotonic(), (text, level))

    def say(self, **message: Any) -> None:
        """An answer to the loop's process; none once it is gone (killed: what is left to
        write, the recording's close above all, is still done)."""
        if self._gone:
            return
        try:
            with self._reply_lock:
                self._reply.write(json.dumps(message) + "\n")
                self._reply.flush()
        except OSError:  # a broken pipe: nobody reads any more
            self._gone = True
            try:  # what is still buffered goes nowhere, not into an error at exit
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, self._reply.fileno())
                os.close(devnull)
            except (OSError, ValueError):
                pass

    def call(self, service: str, payload: bytes) -> Future[dict[str, Any]]:
        """A live view's service call, handed to the loop's process: its answer comes
        back as ``answer`` (``take``)."""
        future: Future[dict[str, Any]] = Future()
        with self._calls_lock:
            if self._gone or self._calls_closed:
                future.set_result(GONE)
                return future
            number = next(self._call_ids)
            self._calls[number] = future
        future.add_done_callback(lambda _: self._calls.pop(number, None))
        self.say(call=number, service=service, payload=payload.hex())
        return future

    def take(self, command: Mapping[str, Any]) -> bool:
        """The commands' thread: what the live view takes at once (an answer, the status
        report, an event, the latch, new controllers); True when it is the view's only."""
        view = self.view
        if "answer" in command:
            future = self._calls.get(int(command["answer"]))
            if future is not None:
                _settle(future, dict(command.get("reply") or {}))
            return True
        if "status" in command:  # for the view, and for the files' /rocoma/status
            if view is not None:
                view.on_status(command["status"])
            if self._files:
                self.facts.statuses.add(float(command.get("time", time.monotonic())),
                                        command["status"])
            return True
        if view is not None:
            if "event" in command:
                view.on_event(command["event"])
            if "latched" in command:
                view.latched = bool(command["latched"])
            if "controllers" in command:
                view.controllers.update({number: name for name, number
                                         in command["controllers"].items()})
        return False

    def unanswered(self) -> None:
        """The loop's process answers no more (its input ended): no call waits for it,
        and a new one is answered at once."""
        with self._calls_lock:
            self._calls_closed = True
            waiting = list(self._calls.values())
        for future in waiting:
            _settle(future, GONE)

    def command(self, command: Mapping[str, Any]) -> None:
        if "event" in command:
            event = command["event"]
            self.facts.on_event(event)
            if self.recording is not None and self.recording.running:
                self.events.append(event)
            if self.flight is not None:
                self.flight.on_event(event)
        if "controllers" in command:
            self.controllers.update({number: name for name, number
                                     in command["controllers"].items()})

    def write(self, closing: bool = False) -> None:
        if self.recording is not None:
            events, self.events = self.events, []
            now = time.time()
            failed = self.recording.write(self.controllers, events, now - time.monotonic(),
                                          math.inf if closing else now - self._hold)
            if failed is not None:
                self.say(error=failed, of="recording")
        flight = self.flight
        if flight is not None:
            if closing and flight.faulted:
                flight.request("shutdown after an e-stop")
            if flight.due(time.monotonic(), closing):
                done = flight.dump(self.controllers)
                if isinstance(done, str):
                    self.say(error=done, of="flight")
                else:
                    self.say(flight_record=str(done[0]), cause=done[1])

    def close(self) -> None:
        if self.view is not None:
            self.view.close()
        if self.recording is not None:
            self.recording.stop()
            for reason in self.recording.errors[1:]:  # the first was said as it happened
                self.say(error=reason, of="recording")
        self.shared.close()


#: the answer to a live view's call once the loop's process answers no more
GONE = {"ok": False, "error": "the manager's process is gone or closing"}


def _settle(future: Future[dict[str, Any]], answer: dict[str, Any]) -> None:
    """``answer`` for a call, unless it timed out meanwhile (cancelled)."""
    try:
        future.set_result(answer)
    except InvalidStateError:  # answered or cancelled: nobody waits for this one
        pass


def _check_mcap() -> None:
    """Every file written here is MCAP (an optional extra): refused at start, not at the
    first e-stop."""
    try:
        import mcap.reader  # noqa: F401
        import zstandard  # noqa: F401  # (mcap_file.py's chunks)
    except ImportError as exc:
        raise RecordingError(f"recording and the flight recorder write MCAP, and "
                             f"{sys.executable} cannot import it ({exc}): pip install "
                             "'rocoma-can[record]'") from exc


def _read_commands(stream: IO[str], writer: Writer,
                   commands: queue.Queue[dict[str, Any] | None]) -> None:
    """stdin, a command a line: what the live view takes at once to it, the rest into
    ``commands``; None at its end."""
    try:
        for line in stream:
            try:
                command = json.loads(line)
                if not writer.take(command):
                    commands.put(command)
            except Exception as exc:  # noqa: BLE001 - one bad line must not deafen the writer
                log.warning("a command it could not take (%s): %.200s", exc, line.rstrip("\n"))
    finally:
        writer.unanswered()
        commands.put(None)


def keep_off(loop_cpus: list[int]) -> None:
    """Every thread of this process (numpy's import starts some) off the CPUs the loop is
    pinned to (``realtime.cpus``), onto the machine's others: a child inherits its parent's
    affinity, and the parent may be pinned whole to the loop's (often isolated) CPU. The
    kernel keeps the set within this process's cpuset; with no CPU left, it stays put."""
    if not loop_cpus or not hasattr(os, "sched_setaffinity"):
        return
    others = set(range(os.cpu_count() or 1)) - set(loop_cpus)
    for task in (os.listdir("/proc/self/task") if os.path.isdir("/proc/self/task")
                 else ["0"]):
        try:
            os.sched_setaffinity(int(task), others)
        except OSError:  # none of them in this cpuset, or the thread just ended
            pass


def run_writer() -> int:
    # A stop signal is the loop's process's to act on: it closes this writer after its
    # torque-off. systemd stops a service by signalling every process of it, this one too,
    # which must live to write the run's end (and ends with its input in any case).
    for stop in (signal.SIGTERM, signal.SIGINT):
        signal.signal(stop, signal.SIG_IGN)
    # what goes wrong here (the live view's SDK: a viewer gone mid-message) is said on the
    # run's stderr in the run's format, saying whose it is; the SDK's INFO records
    # (counted) stay unsaid
    said = logging.StreamHandler(sys.stderr)
    said.setLevel(logging.WARNING)
    said.setFormatter(ConsoleFormatter(clock=True, names=True, who="writer process"))
    logging.getLogger().addHandler(said)
    reply = sys.stdout
    try:
        spec = Spec.from_json(sys.stdin.readline())
        keep_off(spec.loop_cpus)
        writer = Writer(spec, reply)
    except ServeError as exc:
        reply.write(json.dumps({"failed": str(exc), "of": "foxglove"}) + "\n")
        reply.flush()
        return 1
    except (RecordingError, OSError, ValueError, TypeError, KeyError, ImportError) as exc:
        reply.write(json.dumps({"failed": str(exc) if isinstance(exc, RecordingError)
                                else f"{type(exc).__name__}: {exc}"}) + "\n")
        reply.flush()
        return 1
    writer.say(ready=True, foxglove_port=writer.view.port if writer.view else None)
    unwritable = writer.flight.check() if writer.flight is not None else None
    if unwritable is not None:  # said at start, not at the first e-stop that loses its record
        writer.say(error=unwritable, of="flight")
    commands: queue.Queue[dict[str, Any] | None] = queue.Queue()
    threading.Thread(target=_read_commands, args=(sys.stdin, writer, commands), daemon=True,
                     name="commands").start()
    next_write = time.monotonic() + POLL
    while True:
        try:
            command = commands.get(timeout=max(0.0, next_write - time.monotonic()))
        except queue.Empty:
            command = {}
        if command is None:  # the loop's process died: its last seconds are a record
            if writer.flight is not None:
                writer.flight.request("the manager's process ended without closing")
            break
        if command.get("close"):
            break
        writer.command(command)
        if time.monotonic() >= next_write:  # a stream of events does not hold writing up
            writer.write()
            next_write = time.monotonic() + POLL
    if writer.view is not None:  # no call is taken while the last writes run
        writer.view.close()
        writer.view = None
    writer.write(closing=True)
    writer.close()
    writer.say(closed=True)
    return 0


if __name__ == "__main__":
    sys.exit(run_writer())
