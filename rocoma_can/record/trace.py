"""The loop's signals, every cycle, in a ring allocated once; MCAP files written off the loop.

``SignalTrace.record`` runs on the loop thread after each cycle: it copies the cycle's
timing, the manager's state and active controller, and every joint's feedback and command
into one preallocated row (a dozen numpy copies, no allocation), in memory the recording's
writer process shares (rings.py). Everything else happens in that process: ``McapWriter``
turns rows (and CAN frames) into MCAP messages, JSON-encoded with a JSON schema, so
Foxglove and PlotJuggler open the file as it is; mcap_file.py writes the file, the ``mcap``
package reads it (``read_messages``).

Channels: ``/rocoma/cycle`` (one message per cycle: ``t``, ``period``, ``work``, ``late``,
``state``, ``controller``, ``cpu`` (the loop thread's CPU time in ``work``), then per joint
arrays ``position``, ``velocity``, ``torque``,
``command_mode``, ``command_position``, ``command_velocity``, ``command_torque``,
``statusword``, ``cia402_state``, ``error_code``), ``/rocoma/event`` (one message per
manager event: ``kind`` emergency_stop / state_changed / active_controller_changed /
recovery / request (an operator's request and its answer), ``state``, ``controller``,
``cause``) and ``/can/<bus>`` (one message per frame: ``id``,
``data`` as hex, ``dlc``, ``extended``, ``remote``, ``error``, ``fd``, ``sent``: sent by
this manager, not received).
"""
from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, BinaryIO, Protocol

import numpy as np

from ..drivers.protocol.joints import JointCommand, JointState
from ..events import ManagerEvent, ManagerState
from .mcap_file import McapFile
from .pacing import unpaced

if TYPE_CHECKING:
    from .rings import Fields

#: per-joint blocks of a row, in order: (name, where it comes from)
JOINT_FIELDS = ("position", "velocity", "torque", "command_mode", "command_position",
                "command_velocity", "command_torque", "statusword", "cia402_state",
                "error_code")
SCALARS = ("t", "period", "work", "late", "state", "controller", "cpu")
#: /can/<bus> messages between two ``pace`` calls (each a tenth of a row's message or less:
#: benchmarks/README.md, "Figures behind constants")
PACED_FRAMES = 32
#: an MCAP chunk's bytes: each is compressed (zstd) in one call between two ``pace`` calls,
#: so a chunk must compress well within one pause (a 1 MiB one did not: benchmarks/README.md)
CHUNK_SIZE = 128 * 1024
STATE_NAMES = {int(s): s.name for s in ManagerState}


def state_name(code: float) -> str:
    """A row's manager state (its number) by name; an unknown number as itself."""
    return STATE_NAMES.get(int(code), str(int(code)))


class ActiveController(Protocol):
    @property
    def active_controller_name(self) -> str: ...


class RowLayout:
    """Where each signal lies in a row of ``joints`` joints: the scalars, then one block of
    ``len(joints)`` numbers per JOINT_FIELDS entry. The loop's SignalTrace writes rows in
    it; the writer process turns them into messages (``message``)."""

    def __init__(self, joints: Sequence[str]) -> None:
        self.names = list(joints)
        n = len(self.names)
        self.width = len(SCALARS) + n * len(JOINT_FIELDS)
        base = len(SCALARS)
        self.slices = tuple(slice(base + k * n, base + (k + 1) * n)
                            for k in range(len(JOINT_FIELDS)))

    def message(self, row: np.ndarray, controllers: Mapping[int, str]) -> dict[str, Any]:
        """One row as the /rocoma/cycle message (``controllers``: number -> name). A value
        that is not finite is ``null`` (the first row's period, a command's NaN): JSON has
        no NaN, and Foxglove and PlotJuggler parse strict JSON."""
        values = row.tolist()  # plain floats at once: faster than element by element
        finite = np.isfinite(row)
        if not finite.all():
            values = [v if ok else None for v, ok in zip(values, finite.tolist())]
        msg: dict[str, Any] = {"t": values[0], "period": values[1], "work": values[2],
                               "late": values[3], "state": state_name(values[4]),
                               "controller": controllers.get(int(values[5]), ""),
                               "cpu": values[6]}
        for field, where in zip(JOINT_FIELDS, self.slices):
            msg[field] = ([int(v) for v in values[where]] if field in _INTEGER_FIELDS
                          else values[where])
        return msg


class SignalTrace:
    """The last ``capacity`` cycles of signals (a ring). ``record`` is the loop's part.

    ``rows`` (capacity x layout width, default: allocated here) and ``publish`` (told the
    number of rows recorded after each) let the ring lie in memory the recording's writer
    process reads (rings.py). ``known``: controller names numbered from the start, so the
    writer knows every name a row can carry (a controller added later is numbered when
    first seen, and the writer told of it from ``controllers``)."""

    def __init__(self, state: JointState, command: JointCommand, manager: ActiveController,
                 capacity: int, *, rows: np.ndarray | None = None,
                 publish: Callable[[int], None] | None = None,
                 known: Sequence[str] = ()) -> None:
        if capacity < 2:
            raise ValueError(f"a signal trace needs room for 2 cycles or more, got {capacity}")
        self.layout = RowLayout(state.names)
        self.names = self.layout.names
        self.capacity = capacity
        self.count = 0               # cycles recorded so far (the ring's write position)
        shape = (capacity, self.layout.width)
        if rows is not None and rows.shape != shape:
            raise ValueError(f"rows of shape {rows.shape} for a trace of {shape}")
        self._rows = np.zeros(shape) if rows is None else rows
        self._publish = publish if publish is not None else _unpublished
        self._sources = (state.position, state.velocity, state.torque, command.mode,
                         command.position, command.velocity, command.torque,
                         state.statusword, state.cia402_state, state.error_code)
        self._joint_columns = slice(len(SCALARS), None)
        self._manager = manager
        self.controllers: dict[str, int] = {name: k for k, name in enumerate(known)}
        self._previous = float("nan")

    def record(self, now: float, work: float, late: float, state: ManagerState,
               cpu: float) -> None:
        """The loop thread, after each cycle: one row, no allocation. ``cpu``: the loop
        thread's CPU time in ``work``."""
        row = self._rows[self.count % self.capacity]
        row[0] = now
        row[1] = now - self._previous
        row[2] = work
        row[3] = late
        row[4] = state
        name = self._manager.active_controller_name
        number = self.controllers.get(name)
        if number is None:  # a controller seen for the first time: rare
            number = self.controllers[name] = len(self.controllers)
        row[5] = number
        row[6] = cpu
        # every joint block in one call: the blocks lie in the row in the sources' order
        np.concatenate(self._sources, out=row[self._joint_columns])
        self._previous = now
        self.count += 1
        self._publish(self.count)


def _unpublished(count: int) -> None:
    """A trace nobody outside this process reads."""


_INTEGER_FIELDS = {"command_mode", "statusword", "cia402_state", "error_code"}


def cycle_schema(joints: Sequence[str]) -> dict[str, Any]:
    """The JSON schema of /rocoma/cycle (joint names in the description: arrays are in this
    order)."""
    number = {"type": "number"}
    array = {"type": "array", "items": number, "description": "joints: " + ", ".join(joints)}
    props: dict[str, Any] = {"t": number, "period": number, "work": number, "late": number,
                             "state": {"type": "string"}, "controller": {"type": "string"},
                             "cpu": number}
    props.update({f: array for f in JOINT_FIELDS})
    return {"type": "object", "title": "rocoma_can.Cycle", "properties": props}


FRAME_SCHEMA = {"type": "object", "title": "rocoma_can.CanFrame", "properties": {
    "id": {"type": "integer"}, "data": {"type": "string", "description": "hex"},
    "dlc": {"type": "integer"}, "extended": {"type": "boolean"},
    "remote": {"type": "boolean"}, "error": {"type": "boolean"}, "fd": {"type": "boolean"},
    "sent": {"type": "boolean", "description": "sent by this manager, not received"}}}


EVENT_SCHEMA = {"type": "object", "title": "rocoma_can.ManagerEvent", "properties": {
    "kind": {"type": "string",
             "description": "emergency_stop, state_changed, active_controller_changed, "
                            "recovery or request"},
    "state": {"type": "string"}, "controller": {"type": "string"},
    "cause": {"type": "string", "description": "an e-stop's cause; a request's surface, "
                                               "what it asked and the answer"}}}


def event_message(event: ManagerEvent) -> dict[str, Any]:
    """A manager event as plain values (what the writer process is sent), with its
    monotonic ``time`` and the e-stop latch it left (``latched``)."""
    return {"kind": event.kind.value, "state": event.state.name,
            "controller": event.active_controller, "cause": event.cause, "time": event.time,
            "latched": event.latched}


def _frame_tail(flags: int) -> str:
    """The end of a /can/<bus> message for these flags (rings.py's bits)."""
    names = (("extended", 1), ("remote", 2), ("error", 4), ("fd", 8), ("sent", 64))
    return "".join(f',"{name}":{"true" if flags & bit else "false"}' for name, bit in names)


#: every flag combination's message end, made once
_FRAME_TAILS = [_frame_tail(flags) for flags in range(128)]


class McapWriter:
    """An MCAP file of /rocoma/cycle and /can/<bus> messages (mcap_file.py writes it; the
    optional extra ``rocoma-can[record]``). Not thread-safe: one writer thread uses it."""

    def __init__(self, stream: BinaryIO, joints: Sequence[str],
                 pace: Callable[[], None] = unpaced) -> None:
        self._pace = pace  # called between messages (pacing.py: the writer process's)
        self._file = McapFile(stream, chunk_size=CHUNK_SIZE)
        self._cycle = self.json_channel(CYCLE_TOPIC, cycle_schema(joints))
        self._frame_schema = self._file.schema("rocoma_can.CanFrame", "jsonschema",
                                               json.dumps(FRAME_SCHEMA).encode())
        self._events = self.json_channel(EVENT_TOPIC, EVENT_SCHEMA)
        self._buses: dict[str, int] = {}

    def json_channel(self, topic: str, schema: Mapping[str, Any]) -> int:
        """A channel of JSON messages under a JSON schema named by its ``title``."""
        schema_id = self._file.schema(str(schema["title"]), "jsonschema",
                                      json.dumps(schema).encode())
        return self._file.channel(topic, "json", schema_id)

    def add(self, channel: int, ns: int, message: Mapping[str, Any]) -> None:
        self._pace()
        self._file.add(channel, ns, json.dumps(message, separators=(",", ":")).encode())

    def cycles(self, layout: RowLayout, controllers: Mapping[int, str], rows: np.ndarray,
               offset: float) -> None:
        """Rows as messages; ``offset``: add to a row's monotonic time for wall-clock time."""
        channel, add, pace = self._cycle, self._file.add, self._pace
        for row in rows:
            pace()
            add(channel, int((row[0] + offset) * 1e9),
                json.dumps(layout.message(row, controllers), separators=(",", ":")).encode())

    def events(self, events: Iterable[Mapping[str, Any]], offset: float) -> None:
        """Manager events as ``event_message`` makes them (their monotonic ``time`` +
        ``offset``: wall-clock time)."""
        for event in events:
            self._pace()
            message = {key: event[key] for key in ("kind", "state", "controller", "cause")}
            self._file.add(self._events, int((float(event["time"]) + offset) * 1e9),
                           json.dumps(message, separators=(",", ":")).encode())

    def frames(self, bus: str, frames: Sequence[Fields]) -> None:
        """A bus's frames as rings.frame_fields gives them, on /can/<bus>: one message
        each, written PACED_FRAMES at a time."""
        channel = self._buses.get(bus)
        if channel is None:
            channel = self._buses[bus] = self._file.channel(f"/can/{bus}", "json",
                                                            self._frame_schema)
        tails, add_many = _FRAME_TAILS, self._file.add_many
        for first in range(0, len(frames), PACED_FRAMES):
            self._pace()
            part = frames[first:first + PACED_FRAMES]
            add_many(channel, [int(t * 1e9) for t, _, _, _ in part],
                     [(f'{{"id":{cob_id},"data":"{data.lower()}","dlc":{len(data) // 2}'
                       f'{tails[flags & 127]}}}').encode() for _, cob_id, flags, data in part])

    def finish(self) -> None:
        self._file.finish()


class TraceError(ValueError):
    """Why a file is not a rocoma-can trace, in one line (the file is left out: the caller
    names it)."""


#: the channels this package writes and reads back; anything else in a file is passed over
CYCLE_TOPIC, EVENT_TOPIC = "/rocoma/cycle", "/rocoma/event"
#: a cycle message's scalar fields a reader relies on, and their JSON types
_CYCLE_SCALARS: dict[str, tuple[type, ...]] = {
    "t": (int, float), "period": (int, float, type(None)), "work": (int, float),
    "late": (int, float), "state": (str,), "controller": (str,)}


def read_messages(path: str, topics: str | Iterable[str] | None = None,
                  notes: list[str] | None = None
                  ) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """(topic, log time ns, decoded message) of every JSON message in an MCAP file (on
    ``topics``, None: all), in order. Other programs' channels in other encodings are passed
    over; ours in another encoding, or not JSON, raise TraceError. A file cut short (its run
    killed, the power lost, the disk full: no summary, a record half written) is read up to
    its last whole record, and ``notes`` gets a line saying so: what was written stays
    readable; so is a whole file damaged in its middle (a bad sector), up to the damage.
    The MCAP reader's other failures (a foreign or garbage file, nothing whole in it) come
    through as they are."""
    wanted = [topics] if isinstance(topics, str) else None if topics is None else list(topics)
    for channel, message in _messages(path, wanted, notes):
        ours = channel.topic in (CYCLE_TOPIC, EVENT_TOPIC)
        if channel.message_encoding != "json":
            if ours:
                raise TraceError(f"{channel.topic} is encoded as "
                                 f"{channel.message_encoding!r}, not JSON")
            continue
        try:
            decoded = json.loads(message.data)
        except ValueError:  # UnicodeDecodeError too
            if ours:
                raise TraceError(f"a {channel.topic} message is not JSON: "
                                 f"{bytes(message.data[:24])!r}") from None
            continue
        yield channel.topic, message.log_time, decoded


def _messages(path: str, topics: list[str] | None, notes: list[str] | None
              ) -> Iterator[tuple[Any, Any]]:
    """(channel, message) in log-time order: through the file's index where it is whole;
    a file the indexed reader refuses before its first message (a cut one has no footer) is
    read from its start, record by record, up to where it breaks."""
    from mcap.reader import NonSeekingReader, make_reader
    with open(path, "rb") as stream:
        read = 0
        try:
            for _schema, channel, message in make_reader(stream).iter_messages(
                    topics=topics, log_time_order=True):
                read += 1
                yield channel, message
            return
        except Exception as refused:
            if read:  # damaged in the middle of a whole file (a chunk): what came before
                if notes is not None:  # it is kept, as before a cut
                    notes.append(f"damaged ({_reason(refused)} after {read} messages: a "
                                 "part of it cannot be read): read up to the damage")
                return
            stream.seek(0)
            kept: list[tuple[Any, Any]] = []
            try:
                for _schema, channel, message in NonSeekingReader(stream).iter_messages(
                        topics=topics, log_time_order=False):
                    kept.append((channel, message))
            except Exception as cut:
                if not kept:  # nothing here is a whole message: the indexed reader's reason
                    raise refused from None
                if notes is not None:
                    notes.append(f"cut short ({_reason(cut)} after {len(kept)} messages: "
                                 "the run that wrote it did not close it): read up to the "
                                 "cut")
            kept.sort(key=lambda pair: pair[1].log_time)
            yield from kept


def read_trace(path: str, notes: list[str] | None = None
               ) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """The cycles and events of read_messages, each checked (check_cycle, check_event): what
    ``plot`` and ``export`` read (a recording's frames and the live view's channels are not
    decoded: most of a trace's messages). Any failure to read the file (none there, a foreign
    or garbage file) is a TraceError; ImportError stays itself (mcap missing). A file cut
    short is read up to the cut, said in ``notes`` (read_messages)."""
    cycles = events = 0
    joints: int | None = None
    try:
        for topic, log_time, msg in read_messages(path, (CYCLE_TOPIC, EVENT_TOPIC), notes):
            if topic == CYCLE_TOPIC:
                cycles += 1
                joints = check_cycle(msg, cycles, joints)
            elif topic == EVENT_TOPIC:
                events += 1
                check_event(msg, events)
            yield topic, log_time, msg
    except (TraceError, ImportError):
        raise
    except Exception as exc:  # noqa: BLE001 - the reader fails in many ways on a foreign
        # or cut file (OSError, struct.error, McapError, EndOfFile, ValueError)
        raise TraceError(_reason(exc)) from None


def _reason(exc: BaseException) -> str:
    """An exception as one line: its type, and its message where it has one (the MCAP
    reader's end-of-file error has none)."""
    kind = type(exc).__name__
    if kind == "error":  # struct.error: the reader read past a cut file's end
        kind = f"{type(exc).__module__}.error"
    text = " ".join(str(exc).split())
    return f"{kind}: {text}" if text else kind


def check_cycle(msg: Any, number: int, joints: int | None = None) -> int:
    """The joint count of cycle message ``number`` (from 1), whose arrays all hold
    ``joints`` numbers (None: as its ``position`` does); TraceError says what is wrong with
    it, since another program's messages can sit on our channel."""
    where = f"{CYCLE_TOPIC} message {number}"
    if not isinstance(msg, dict):
        raise TraceError(f"{where} is {_json_kind(msg)}, not an object")
    for key, kinds in _CYCLE_SCALARS.items():
        value = msg.get(key)
        if key not in msg:
            raise TraceError(f"{where} has no {key!r}")
        if not isinstance(value, kinds) or isinstance(value, bool):
            raise TraceError(f"{where}: {key!r} is {_json_kind(value)}, not "
                             f"{'text' if kinds == (str,) else 'a number'}"
                             f"{' or null' if type(None) in kinds else ''}")
    for key in JOINT_FIELDS:
        values = msg.get(key)
        if not isinstance(values, list):
            raise TraceError(f"{where} has no {key!r} array" if key not in msg else
                             f"{where}: {key!r} is {_json_kind(values)}, not an array")
        if joints is None:
            joints = len(values)
        if len(values) != joints:
            raise TraceError(f"{where}: {key!r} has {len(values)} joints, the trace "
                             f"{joints}")
        for value in values:  # (null: a value that was not finite, a NaN command)
            if not isinstance(value, (int, float, type(None))) or isinstance(value, bool):
                raise TraceError(f"{where}: {key!r} holds {_json_kind(value)}, not a "
                                 "number or null")
    assert joints is not None  # JOINT_FIELDS is not empty
    return joints


def check_event(msg: Any, number: int) -> None:
    """TraceError unless event message ``number`` is an object of text fields."""
    where = f"{EVENT_TOPIC} message {number}"
    if not isinstance(msg, dict):
        raise TraceError(f"{where} is {_json_kind(msg)}, not an object")
    for key in ("kind", "state", "controller", "cause"):
        if not isinstance(msg.get(key, ""), str):
            raise TraceError(f"{where}: {key!r} is {_json_kind(msg[key])}, not text")


def _json_kind(value: Any) -> str:
    """A JSON value's kind with a glimpse of it, for a one-line reason."""
    kinds = {dict: "an object", list: "an array", str: "text", bool: "a boolean",
             int: "a number", float: "a number", type(None): "null"}
    glimpse = repr(value)
    glimpse = glimpse if len(glimpse) <= 24 else glimpse[:24] + "..."
    return f"{kinds.get(type(value), type(value).__name__)} ({glimpse})"


def recorded_joint_names(path: str, joints: int) -> list[str] | None:
    """The ``joints`` joint names the cycle schema's description carries ("joints: a, b"),
    None where a file has none that fit (another writer's schema, an older file)."""
    from mcap.reader import make_reader
    try:
        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        for schema in (summary.schemas.values() if summary is not None else ()):
            if schema.name == "rocoma_can.Cycle":
                text = json.loads(schema.data)["properties"]["position"]["description"]
                names = [n.strip() for n in text.removeprefix("joints:").split(",")]
                if len(names) == joints and all(names) and len(set(names)) == joints:
                    return names
    except Exception:  # noqa: BLE001 - names are a nicety: a foreign schema, a cut file
        pass
    return None
