"""The messages the node publishes and answers with, built from plain values (rosbags'
message classes, through ``Interfaces.message``): joint states, diagnostics, log records,
strings, Trigger answers and the controller list."""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from .interfaces import (
    DIAGNOSTIC_ARRAY,
    JOINT_STATE,
    LIST_CONTROLLERS,
    LOG,
    STRING,
    SWITCH_CONTROLLER,
    TRIGGER,
    Interfaces,
    Service,
)

#: rcl_interfaces/Log levels; diagnostic_msgs/DiagnosticStatus levels
INFO, WARN, ERROR = 20, 30, 40
OK_LEVEL, WARN_LEVEL, ERROR_LEVEL = 0, 1, 2


def ros_time(i: Interfaces, ns: int) -> Any:
    return i.message("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000,
                     nanosec=ns % 1_000_000_000)


def header(i: Interfaces, ns: int) -> Any:
    return i.message("std_msgs/msg/Header", stamp=ros_time(i, ns), frame_id="")


def joint_state(i: Interfaces, ns: int, names: Sequence[str], position: np.ndarray,
                velocity: np.ndarray, effort: np.ndarray) -> bytes:
    """SI units, as the drives reported them last (float64 arrays, copied by the caller)."""
    return i.encode(i.message(JOINT_STATE, header=header(i, ns), name=list(names),
                              position=position, velocity=velocity, effort=effort),
                    JOINT_STATE)


def diagnostics(i: Interfaces, ns: int, node: str, report: Mapping[str, Any],
                buses: Mapping[str, str]) -> bytes:
    """The manager's status and one per drive (state, fault, NMT, bus and its load) from
    the status report (``status --json``'s document); ``buses``: each drive's bus."""
    def values(pairs: Iterable[tuple[str, object]]) -> list[Any]:
        return [i.message("diagnostic_msgs/msg/KeyValue", key=k, value=_text(v))
                for k, v in pairs]

    def status(level: int, name: str, message: str, hardware_id: str,
               pairs: Iterable[tuple[str, object]]) -> Any:
        return i.message("diagnostic_msgs/msg/DiagnosticStatus", level=level, name=name,
                         message=message, hardware_id=hardware_id, values=values(pairs))
    state = str(report.get("state", "?"))
    cycle = report.get("cycle") or {}
    manager = status(
        OK_LEVEL if state == "OK" else WARN_LEVEL if state == "EMERGENCY" else ERROR_LEVEL,
        f"{node}: manager", f"{state}, {report.get('active', '?')}"
        + (", e-stop latched" if report.get("latched") else ""), node,
        [("state", state), ("controller", report.get("active")),
         ("latched", report.get("latched")), ("last e-stop", report.get("estop_cause")),
         ("cycles", cycle.get("cycles")), ("overruns", cycle.get("overruns")),
         ("bus fault", report.get("bus_fault"))])
    loads = {b.get("name"): b for b in report.get("buses") or []}
    drives = []
    for d in report.get("drives") or []:
        fault = d.get("fault")
        bus: Mapping[str, Any] = (loads.get(buses.get(str(d.get("name")), ""))
                                  or next(iter(loads.values()), {}))
        level = ERROR_LEVEL if fault else OK_LEVEL if d.get("enabled") else WARN_LEVEL
        drives.append(status(
            level, f"{node}: {d.get('name')}", fault or str(d.get("cia402_state")),
            f"node {d.get('node_id')}",
            [("phase", d.get("phase")), ("cia402", d.get("cia402_state")),
             ("enabled", d.get("enabled")), ("fault", fault), ("nmt", d.get("nmt_state")),
             ("heartbeat age s", d.get("heartbeat_age")), ("bus", bus.get("name")),
             ("bus fault", bus.get("fault")), ("bus load", bus.get("load"))]))
    return i.encode(i.message(DIAGNOSTIC_ARRAY, header=header(i, ns),
                              status=[manager, *drives]), DIAGNOSTIC_ARRAY)


def log(i: Interfaces, ns: int, node: str, level: int, text: str) -> bytes:
    return i.encode(i.message(LOG, stamp=ros_time(i, ns), level=level, name=node, msg=text,
                              file="", function="", line=0), LOG)


def string(i: Interfaces, text: str) -> bytes:
    return i.encode(i.message(STRING, data=text), STRING)


def trigger_response(i: Interfaces, success: bool, message: str) -> bytes:
    name = Service(TRIGGER).response
    return i.encode(i.message(name, success=success, message=message), name)


def switch_response(i: Interfaces, ok: bool, message: str) -> bytes:
    """SwitchController's answer: ``message`` where the definitions served have it."""
    name = Service(SWITCH_CONTROLLER).response
    fields: dict[str, Any] = {"ok": ok}
    if i.has_field(name, "message"):
        fields["message"] = message
    return i.encode(i.message(name, **fields), name)


def controller_list(i: Interfaces, controllers: Sequence[tuple[str, str, str]]) -> bytes:
    """ListControllers' answer: (name, type, state) each, every other field empty."""
    name = Service(LIST_CONTROLLERS).response
    state = "controller_manager_msgs/msg/ControllerState"
    extra: dict[str, Any] = ({"is_async": False, "update_rate": 0}
                             if i.has_field(state, "is_async") else {})
    if i.has_field(state, "exported_state_interfaces"):
        extra["exported_state_interfaces"] = []
    return i.encode(i.message(name, controller=[
        i.message(state, name=n, state=s, type=t, claimed_interfaces=[],
                  required_command_interfaces=[], required_state_interfaces=[],
                  is_chainable=False, is_chained=False, reference_interfaces=[],
                  chain_connections=[], **extra)
        for n, t, s in controllers]), name)


def _text(value: object) -> str:
    if value is None:
        return ""
    if isinstance(value, float) and not math.isfinite(value):
        return "nan"
    return str(value)
