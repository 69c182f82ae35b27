"""The messages of the live view (foxglove.py), as the MCAP recordings carry them too: one
set of channels, so a recording opens in Foxglove with the live view's layout. Each channel
is a ``Channel`` constant (topic, schema name, JSON schema); each builder takes plain values
(floats, lists, str) and returns the message as a dict ready for ``json.dumps``. Pure Python,
neither foxglove-sdk nor numpy: the recording's writer process imports it for nothing.

Channels, every one JSON with its JSON schema:

* ``/joint_states`` (``rocoma.JointStates``): ``timestamp`` and per joint ``name``,
  ``position`` (rad), ``velocity`` (rad/s), ``effort`` (Nm); ``null`` for a joint without
  feedback (JSON has no NaN);
* ``/rocoma/manager`` (``rocoma.Manager``): ``state``, ``controller``, ``latched`` (the
  e-stop latch), ``cause`` (the last e-stop's), the loop's ``cycles``, ``overruns`` and
  ``overruns_waiting`` (rocoma_can/overrun.py), and
  the live view's own counters (``foxglove``, live only);
* ``/rocoma/status`` (``rocoma.Status``): the status report as ``status --json`` prints it
  (cycle statistics, each bus's load and errors, the drives);
* ``/rocoma/log`` (``foxglove.Log``): a line per manager event and per command;
* ``/robot_description`` (``std_msgs/String``): the config's URDF as ``data``, what
  Foxglove's 3D panel draws (its URDF layer takes a topic of that schema name);
* ``/tf`` (``foxglove.FrameTransforms``): the parent-to-child transform of every URDF joint
  at the joint's position (urdf.py), which move the drawn links.

The last two only with a URDF in the config (``urdf:``).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..audit import event_text

#: foxglove.Log levels (an e-stop is a WARNING: the manager did what it must)
INFO, WARNING = 2, 3


@dataclass(frozen=True, eq=False)
class Channel:
    """A channel's topic and JSON schema; the schema's ``title`` is its name."""
    topic: str
    schema: dict[str, Any]

    @property
    def schema_name(self) -> str:
        return str(self.schema["title"])


def _schema(title: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": properties}


_NUMBERS = {"type": "array", "items": {"type": ["number", "null"]}}
_TIME = {"type": "object", "title": "time", "properties": {
    "sec": {"type": "integer", "minimum": 0},
    "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}
_XYZ = {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}

JOINT_STATES = Channel("/joint_states", _schema("rocoma.JointStates", {
    "timestamp": _TIME, "name": {"type": "array", "items": {"type": "string"}},
    "position": _NUMBERS, "velocity": _NUMBERS, "effort": _NUMBERS}))
MANAGER = Channel("/rocoma/manager", _schema("rocoma.Manager", {
    "state": {"type": "string"}, "controller": {"type": "string"},
    "latched": {"type": "boolean"}, "cause": {"type": "string"},
    "cycles": {"type": "integer"}, "overruns": {"type": "integer"},
    "overruns_waiting": {"type": "integer"},
    "foxglove": {"type": "object"}}))
STATUS = Channel("/rocoma/status", _schema("rocoma.Status", {}))
LOG = Channel("/rocoma/log", _schema("foxglove.Log", {
    "timestamp": _TIME, "level": {"type": "integer"}, "message": {"type": "string"},
    "name": {"type": "string"}, "file": {"type": "string"}, "line": {"type": "integer"}}))
ROBOT_DESCRIPTION = Channel("/robot_description", _schema("std_msgs/String", {
    "data": {"type": "string"}}))
TRANSFORMS = Channel("/tf", _schema("foxglove.FrameTransforms", {
    "transforms": {"type": "array", "items": _schema("foxglove.FrameTransform", {
        "timestamp": _TIME, "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _schema("foxglove.Vector3", _XYZ),
        "rotation": _schema("foxglove.Quaternion", {**_XYZ, "w": {"type": "number"}})})}}))

#: served always; ROBOT only with a URDF in the config
MANAGER_CHANNELS = (JOINT_STATES, MANAGER, STATUS, LOG)
ROBOT = (ROBOT_DESCRIPTION, TRANSFORMS)

_ERROR = {"type": "string", "description": "why it was refused or failed"}
_STATE_ANSWER = _schema("rocoma.StateAnswer", {
    "ok": {"type": "boolean"}, "state": {"type": "string"},
    "pending": {"type": "boolean", "description": "the loop had not acted on it yet"},
    "error": _ERROR})
_STOP_REQUEST = {"title": "rocoma.StopRequest",
                 "description": "anything: a stop acts whatever it carries (never read)"}
_EMPTY_REQUEST = _schema("rocoma.EmptyRequest", {})
#: each service's request and answer as JSON schemas (what Foxglove's Service Call panel
#: shows): a switch names its controller; a stop reads nothing; clear and recover take
#: nothing; every answer may instead be ``{"ok": false, "error"}`` when the manager's
#: process did not answer
SERVICES: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "switch": (_schema("rocoma.SwitchRequest", {"controller": {
        "type": ["string", "integer"],
        "description": "a controller's name, or its number in rocoma-can list"}}),
        _schema("rocoma.SwitchAnswer", {
            "result": {"enum": ["SWITCHED", "RUNNING", "NOT_FOUND", "ERROR"]},
            "ok": {"type": "boolean"}, "error": _ERROR})),
    "estop": (_STOP_REQUEST, _STATE_ANSWER),
    "failproof": (_STOP_REQUEST, _STATE_ANSWER),
    "clear": (_EMPTY_REQUEST, _STATE_ANSWER),
    "recover": (_EMPTY_REQUEST, _STATE_ANSWER),
}


def stamp(ns: int) -> dict[str, int]:
    """A foxglove time from nanoseconds since the epoch."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _numbers(values: Iterable[float]) -> list[float | None]:
    return [v if math.isfinite(v) else None for v in values]


def joint_states(ns: int, names: Sequence[str], position: Iterable[float],
                 velocity: Iterable[float], effort: Iterable[float]) -> dict[str, Any]:
    return {"timestamp": stamp(ns), "name": list(names), "position": _numbers(position),
            "velocity": _numbers(velocity), "effort": _numbers(effort)}


def manager(state: str, controller: str, latched: bool, cause: str, cycles: int,
            overruns: tuple[int, int], view: Mapping[str, Any] | None = None
            ) -> dict[str, Any]:
    """``overruns``: the loop's, and those of them that waited (rocoma_can/overrun.py);
    ``view``: the live view's own counters (a recording has none)."""
    message = {"state": state, "controller": controller, "latched": latched, "cause": cause,
               "cycles": cycles, "overruns": overruns[0], "overruns_waiting": overruns[1]}
    return message if view is None else {**message, "foxglove": dict(view)}


def log(ns: int, text: str, level: int = INFO) -> dict[str, Any]:
    return {"timestamp": stamp(ns), "level": level, "message": text, "name": "rocoma-can",
            "file": "", "line": 0}


def event_log(event: Mapping[str, Any]) -> tuple[str, int]:
    """A manager event (as record/trace.event_message gives it) as a log line and its
    level: the audit trail's wording (rocoma_can/audit.py), one for the console and the
    recordings."""
    text, level = event_text(event)
    return text, WARNING if level >= logging.WARNING else INFO


def robot_description(urdf: str) -> dict[str, Any]:
    return {"data": urdf}


def frame_transforms(ns: int, transforms: Iterable[tuple[str, str, Sequence[float],
                                                           Sequence[float]]]
                     ) -> dict[str, Any]:
    """``transforms``: (parent, child, (x, y, z), (x, y, z, w)) each, as urdf.Robot's."""
    t = stamp(ns)
    return {"transforms": [
        {"timestamp": t, "parent_frame_id": parent, "child_frame_id": child,
         "translation": dict(zip("xyz", translation)),
         "rotation": dict(zip("xyzw", rotation))}
        for parent, child, translation, rotation in transforms]}
