"""Recording and the live view for ``rocoma-can run`` and the demo: the loop's side of
them, and the writer process it starts (the flight recorder, on by default, ``--record``
and ``--foxglove``'s server).

The loop must not pay for recording: JSON, MCAP, candump text and the disk cost a good
share of a core at 1 kHz with 12 drives, and in the loop's interpreter they took that from
the loop. So the loop's process only copies, into rings in shared memory (rings.py): each
cycle's signal row (trace.SignalTrace) and each frame its buses carried (a copy each:
the hardware's own reader hands the received ones over, BusPort the sent ones; no second
socket). Everything else runs in a process of its own (writer.py), niced, on the other core
(never on CPUs the loop is pinned to, ``loop_cpus``: realtime.cpus, while there are others):
it reads the rings every 50 ms, writes ``--record``'s files and, on an e-stop, a flight
record from the rings' last ``seconds``, and serves the live view (live/server.py) from the
same rows: only the answers to its service calls and, while a viewer watches it, the
status report are made in this process (live/foxglove.py's FoxgloveView).

Manager events (and the live view's answers and status reports) reach the writer through a
pipe, sent by a thread of this process from a bounded queue (full: dropped, counted in
``events_dropped``). The writer answers on another
pipe: each flight record's path (said through ``announce``, or logged) and each failure (a
full disk: the first one logged as a warning, all in ``errors``). If the writer dies, the
loop runs on, the reason is logged and in the recording's and the flight recorder's
``errors``, and the close does not wait for it; if this process dies, the writer writes
what the rings hold and ends.
"""
from __future__ import annotations

import json
import logging
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

from ..drivers.protocol.joints import JointCommand, JointState
from ..events import ManagerEvent
from ..live.foxglove import FoxgloveError
from ..live.urdf import Robot
from .can_log import RecordingError
from .flight import MAX_FRAMES_PER_SECOND
from .rings import FrameRing, SharedFile, layout
from .trace import RowLayout, SignalTrace, event_message
from .writer import Spec

log = logging.getLogger(__name__)

#: what a recording keeps at least, s: how far the writer may fall behind before a ring
#: overwrites what it has not written
SLACK = 10.0
#: how long the writer process may take to start (imports) and to finish (its last
#: writes, a flight record), s
START_WAIT = 30.0
CLOSE_WAIT = 30.0
#: manager events queued for the writer at most
EVENT_QUEUE = 4096
#: s between the status reports that go into the recording and the flight records
#: (``status_source`` holds this process's interpreter for a fair share of a 1 kHz cycle,
#: and in the demo some reports made a cycle overrun: benchmarks/README.md, "Figures behind
#: constants"; the per-cycle statistics are in every /rocoma/cycle row anyway)
STATUS_PERIOD = 2.0
#: the writer's niceness: the loop's process comes first when the cores are busy
NICE = 19


class LiveView(Protocol):
    """The live view's side in this process (live/foxglove.py's FoxgloveView)."""
    def settings(self) -> dict[str, Any]: ...
    def served(self, port: int, send: Callable[[dict[str, Any]], bool]) -> None: ...
    def on_reply(self, reply: dict[str, Any]) -> None: ...
    def gone(self) -> None: ...


class RecordedManager(Protocol):
    """What the recorder reads of the manager (besides its events)."""
    @property
    def active_controller_name(self) -> str: ...
    @property
    def estop_latched(self) -> bool: ...


@dataclass
class FlightStatus:
    """The flight recorder as the run sees it: its directory, each record written (in
    order), each failure."""
    directory: Path
    dumps: list[Path] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


@dataclass
class RecordingStatus:
    """``--record DIR`` as the run sees it: ``DIR/trace.mcap`` and a log per bus; every
    failure, the first first (the recording then stopped)."""
    directory: Path
    errors: list[str] = field(default_factory=list)

    @property
    def path(self) -> Path:
        return self.directory / "trace.mcap"


@dataclass(frozen=True)
class BusToRecord:
    """A bus as its recording names it: its config label, its channel (the candump
    files'), CAN FD or not (the size of a frame record)."""
    label: str
    channel: str
    fd: bool


class Recorder:
    """The rings, the writer process and the threads that talk to it (see module).
    ``view``: the live view the writer process serves (None: none); without ``record``
    and ``flight`` no frame is kept (``frame_taps`` is empty)."""

    def __init__(self, state: JointState, command: JointCommand, manager: RecordedManager,
                 rate: float, buses: Sequence[BusToRecord], *, record: str | None = None,
                 flight: str | None = None, seconds: float = 10.0,
                 controllers: Sequence[str] = (), robot: Robot | None = None,
                 announce: Callable[[str], None] | None = None,
                 view: LiveView | None = None, loop_cpus: Collection[int] = ()) -> None:
        if record is None and flight is None and view is None:
            raise ValueError("a recorder records or serves something: record, flight, "
                             "view")
        if record is None and flight is None:
            buses = ()  # the live view reads rows only
        keep = max(seconds if flight is not None else 0.0, SLACK)
        frames = int(MAX_FRAMES_PER_SECOND * keep)
        specs = layout([("rows", max(2, int(rate * keep)), RowLayout(state.names).width,
                         False)] + [(f"{bus.label} {way}", frames, 0, bus.fd)
                                    for bus in buses for way in ("received", "sent")])
        self._shared = SharedFile(specs[-1].offset + specs[-1].size)
        rows = specs[0]
        self.trace = SignalTrace(state, command, manager, rows.capacity,
                                 rows=self._shared.array(rows),
                                 publish=lambda n: self._shared.publish(rows, n),
                                 known=controllers)
        #: per bus, in order: (received, sent) rings, for CanopenHardware.record_frames
        self.frame_taps = [(FrameRing(self._shared, specs[1 + 2 * k], sent=False),
                            FrameRing(self._shared, specs[2 + 2 * k], sent=True))
                           for k in range(len(buses))]
        self.flight = FlightStatus(Path(flight)) if flight is not None else None
        self.recording = RecordingStatus(Path(record)) if record is not None else None
        self.events_dropped = 0
        self._writer_lost = False  # said (_lost)
        self.status_errors = 0
        self._announce = announce
        self._view = view
        self._sent_controllers = dict(self.trace.controllers)
        #: the status report (``rocoma-can status --json``'s), sent once every STATUS_PERIOD
        #: for the files' /rocoma/status; set once what it reads exists (runtime/system.py)
        self.status_source: Callable[[], dict[str, Any]] | None = None
        self._files = record is not None or flight is not None
        self._manager, self._latched = manager, manager.estop_latched
        self._queue: queue.Queue[str | None] = queue.Queue(maxsize=EVENT_QUEUE)
        self._ready: queue.Queue[dict[str, Any]] = queue.Queue()
        self._closing = threading.Event()  # close(): the sender ends with the queue
        self._ended = threading.Event()    # the writer's output ended: it said all it will
        spec = Spec(self._shared.fd, self._shared.size, rows,
                    {bus.label: (bus.channel, [specs[1 + 2 * k], specs[2 + 2 * k]])
                     for k, bus in enumerate(buses)},
                    list(state.names), dict(self.trace.controllers), record, flight, seconds,
                    rate, robot.as_json() if robot is not None else None,
                    view.settings() if view is not None else None, sorted(loop_cpus),
                    latched=self._latched)
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "rocoma_can.record.writer"], stdin=subprocess.PIPE,
                stdout=subprocess.PIPE, text=True, pass_fds=(self._shared.fd,),
                start_new_session=True,  # a Ctrl-C is the run's to handle: the writer is told
                preexec_fn=lambda: os.nice(NICE))  # noqa: PLW1509 - no threads in the child yet
        except (OSError, subprocess.SubprocessError) as exc:
            self._shared.close()
            raise RecordingError(f"cannot start the recording's writer process "
                                 f"({sys.executable}): {exc}") from exc
        self._threads: list[threading.Thread] = []
        self._sender: threading.Thread | None = None
        try:
            self._stdin: IO[str] = self._process.stdin  # type: ignore[assignment]
            self._stdin.write(spec.to_json() + "\n")
            self._stdin.flush()
            self._start_thread(self._read_replies, "recorder-replies")
            try:
                first = self._ready.get(timeout=START_WAIT)
            except queue.Empty:
                raise RecordingError(f"the recording's writer process did not start within "
                                     f"{START_WAIT:g} s") from None
            if "failed" in first:
                if first.get("of") == "foxglove":
                    raise FoxgloveError(str(first["failed"]))
                raise RecordingError(str(first["failed"]))
            self._sender = self._start_thread(self._send, "recorder-events")
            if view is not None:
                view.served(int(first["foxglove_port"]), self.send)
        except BaseException:
            self._stop_process()
            raise

    @property
    def pid(self) -> int:
        """The writer process's (ps, top: its CPU is what recording and the view cost)."""
        return int(self._process.pid)

    def _start_thread(self, target: Callable[[], None], name: str) -> threading.Thread:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)
        return thread

    def on_event(self, event: ManagerEvent) -> None:
        """A manager subscriber (its event thread): queued for the writer, never waits."""
        self.send({"event": event_message(event)})

    def send(self, message: dict[str, Any]) -> bool:
        """``message`` queued for the writer (any thread, never waits); False: the queue
        is full and it is dropped (counted in ``events_dropped``)."""
        try:
            self._queue.put_nowait(json.dumps(message))
        except queue.Full:
            self.events_dropped += 1
            return False
        return True

    def _send(self) -> None:
        """The events, new controller numbers and (into the files) a status report every
        STATUS_PERIOD to the writer, then ``close``."""
        next_status = time.monotonic() + STATUS_PERIOD
        while True:
            try:
                line = self._queue.get(timeout=0.2)
            except queue.Empty:  # (a close that found the queue full: now it is empty)
                line = None if self._closing.is_set() else ""
            lines = []
            latched = self._manager.estop_latched
            if latched != self._latched:  # a clear is no event: looked at here
                self._latched = latched
                lines.append(json.dumps({"latched": latched}))
            known = self.trace.controllers
            if len(known) != len(self._sent_controllers):  # one added since the start: rare
                new = {k: v for k, v in list(known.items()) if k not in self._sent_controllers}
                self._sent_controllers.update(new)
                lines.append(json.dumps({"controllers": new}))
            lines.append(json.dumps({"close": True}) if line is None else line)
            now = time.monotonic()
            if now >= next_status and line is not None:  # after what came before it
                next_status = now + STATUS_PERIOD
                lines.append(self._status_line(now))
            try:
                self._stdin.write("".join(f"{text}\n" for text in lines if text))
                self._stdin.flush()
                if line is None:
                    self._stdin.close()
                    return
            except (OSError, ValueError):  # the writer is gone: said by _read_replies
                return

    def _status_line(self, now: float) -> str:
        """The status report as a line for the writer ("" when there is none to send)."""
        source = self.status_source
        if source is None or not self._files:
            return ""
        try:
            return json.dumps({"status": source(), "time": now})
        except Exception as exc:  # noqa: BLE001 - a report that fails is said, never fatal
            self.status_errors += 1
            if self.status_errors == 1:
                log.warning("recording: the status report failed: %s", exc)
            return ""

    def _read_replies(self) -> None:
        stdout = self._process.stdout
        assert stdout is not None
        started = closed = False
        try:
            for line in stdout:
                try:
                    reply = json.loads(line)
                except ValueError:
                    continue
                if "ready" in reply or "failed" in reply:
                    started = "ready" in reply
                    self._ready.put(reply)
                elif "flight_record" in reply:
                    self._flight_record(Path(reply["flight_record"]), str(reply["cause"]))
                elif "error" in reply:
                    self._error(str(reply["error"]), reply.get("of") == "flight")
                elif "closed" in reply:
                    closed = True
                elif self._view is not None:
                    try:
                        self._view.on_reply(reply)
                    except Exception:  # one bad reply must not end this thread's reading
                        log.exception("the live view could not take %.200s", line)
            if not closed:
                try:
                    code: int | None = self._process.wait(1.0)
                except subprocess.TimeoutExpired:
                    code = None
                reason = f"the recording's writer process ended (exit code {code})"
                if started:  # (a start that failed raises it)
                    self._lost(reason)
                self._ready.put({"failed": reason})
        finally:
            self._ended.set()

    def _lost(self, reason: str) -> None:
        """The writer is gone or stuck: said for the recording and the flight recorder,
        once (a stuck writer the close gives up on is then killed, and ends)."""
        if self._writer_lost:
            log.debug("the recording's writer process: %s", reason)
            return
        self._writer_lost = True
        if self.recording is not None:
            self._error(reason, False)
        if self.flight is not None:
            self._error(f"{reason}: no flight records from now on", True)
        if self._view is not None:
            self._view.gone()
            log.error("the Foxglove live view is gone: %s", reason)

    def _flight_record(self, path: Path, cause: str) -> None:
        if self.flight is not None:
            self.flight.dumps.append(path)
        if self._announce is not None:  # said once: by the announcer, else in the log
            self._announce(f"flight record ({cause}): {path}")
        else:
            log.warning("flight record (%s): %s", cause, path)

    def _error(self, reason: str, of_flight: bool) -> None:
        """Said, then kept in ``errors``: whoever sees it there (the run's end, a test) finds
        it said already."""
        if of_flight:
            log.error("flight recorder: %s", reason)
            if self.flight is not None:
                self.flight.errors.append(reason)
            return
        status = self.recording
        if status is None:
            return
        if not status.errors:
            log.warning("recording to %s stopped, the loop runs on: %s", status.directory,
                        reason)
        else:
            log.debug("recording to %s: %s", status.directory, reason)
        status.errors.append(reason)

    def close(self) -> None:
        """After the loop's last cycle: the writer writes everything (a last flight record
        after an e-stop), answers and ends; bounded by CLOSE_WAIT, then it is killed. A
        writer that died has nothing more to say: no wait. A Ctrl-C during the wait (an
        impatient second stop) kills the writer and goes on up: nothing is left running."""
        self._closing.set()
        try:
            self._queue.put_nowait(None)
        except queue.Full:  # the sender ends once it has sent what is queued
            pass
        try:
            if not self._ended.wait(CLOSE_WAIT):
                self._lost(f"the recording's writer process did not finish within "
                           f"{CLOSE_WAIT:g} s")
        except BaseException:
            self._process.kill()  # (what it had not written yet is lost: asked for)
            raise
        finally:
            self._stop_process()

    def _stop_process(self) -> None:
        stdin = self._process.stdin
        sender = self._sender
        if sender is None:  # a start cut short (a Ctrl-C, the writer's failure): told to
            _close_quietly(stdin, '{"close": true}\n')  # end, its input's end is no death
        elif not sender.is_alive():  # (a sender blocked on a full pipe
            _close_quietly(stdin)    # holds it: it ends with the writer)
        try:  # (a start that failed: its end of input tells the writer to end)
            self._process.wait(5.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait(5.0)
        for thread in self._threads:
            thread.join(5.0)
        _close_quietly(stdin)
        _close_quietly(self._process.stdout)
        self._shared.close()


def _close_quietly(stream: IO[str] | None, last: str = "") -> None:
    """A pipe to or from the writer, closed whatever the writer did (gone: its unsent
    input fails), after ``last`` (a last command) when there is one."""
    try:
        if stream is not None:
            if last:
                stream.write(last)
            stream.close()
    except (OSError, ValueError):
        pass

