"""The ``zenoh:`` section of the run config (docs/fleet.md), which the CLI's ``--zenoh``
flags set too: FleetConfig, and ``parse_fleet`` checking it as every config check does
(each problem "zenoh.KEY: ..."). The bridge (bridge.py) runs what it says.
"""
from __future__ import annotations

import difflib
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

MODES = ("peer", "client")
_KEYS = {"prefix", "mode", "connect", "listen", "multicast", "allow_commands", "deadman",
         "required", "drives_period", "alive_timeout", "config_file"}




def default_prefix() -> str:
    return f"rocoma/{_key_chunk(socket.gethostname())}"


def _key_chunk(text: str) -> str:
    """A Zenoh key-expression chunk: no '/', '*', '$', '?', '#' and not empty."""
    out = "".join(c if c.isalnum() or c in "-_." else "-" for c in text)
    return out or "host"


def key_problem(key: Any) -> str | None:
    """Why ``key`` is no concrete Zenoh key expression (None: it is one): chunks between
    '/' not empty, no wildcard or special character ('*', '$', '?', '#'). A prefix with a
    wildcard would serve, and act on, queries meant for other managers."""
    if not isinstance(key, str) or not key:
        return "expected a key expression such as rocoma/robot1"
    if any(c in key for c in "*$?#") or any(not chunk for chunk in key.split("/")):
        return (f"{key!r} is not a concrete key expression (no empty chunk, no leading or "
                "trailing '/', none of * $ ? #)")
    return None


@dataclass
class FleetConfig:
    """The ``zenoh:`` config section (docs/fleet.md); the CLI flags set the same. ``mode``
    and ``multicast`` left None keep what ``config_file`` (or Zenoh's default: peer,
    multicast scouting on) says."""
    prefix: str = field(default_factory=default_prefix)
    mode: str | None = None
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    multicast: bool | None = None   # Zenoh's multicast scouting
    allow_commands: bool = False    # switch, clear, recover over Zenoh
    deadman: str | None = None      # a liveliness key: e-stop when it vanishes
    required: bool = True           # Zenoh unavailable at start-up: error (else a warning)
    drives_period: float = 1.0      # s between <prefix>/drives publications
    alive_timeout: float = 1.0      # s without a cycle before <prefix>/alive is withdrawn
    config_file: str | None = None  # a Zenoh JSON5 config (access control, TLS) beneath ours


def known_section(section: Any, known: set[str], where: str, problems: list[str]) -> bool:
    """Whether ``section`` is a mapping (else said); each key of it not ``known`` said with
    the closest known one. The zenoh: and ros2: sections' first check."""
    if not isinstance(section, Mapping):
        problems.append(f"{where}: expected a mapping, got {type(section).__name__}")
        return False
    for key in sorted(set(section) - known, key=str):
        close = difflib.get_close_matches(str(key), known, n=1)
        hint = f", did you mean {close[0]!r}?" if close else ""
        problems.append(f"{where}.{key}: unknown key{hint} (known: {', '.join(sorted(known))})")
    return True


def parse_fleet(section: Any, problems: list[str], where: str = "zenoh",
                base: FleetConfig | None = None) -> FleetConfig | None:
    """The ``zenoh:`` section (None: absent) over ``base`` (default: the defaults), every
    problem as "zenoh.KEY: ..."; the CLI's flags come through here too."""
    if section is None or not known_section(section, _KEYS, where, problems):
        return None
    out = base or FleetConfig()
    _take_names(section, out, where, problems)
    _take_endpoints(section, out, where, problems)
    _take_switches(section, out, where, problems)
    if section.get("deadman") is not None:
        why = key_problem(section["deadman"])
        if why:
            problems.append(f"{where}.deadman: {why} (a liveliness key, e.g. "
                            "rocoma/operators/console1)")
        else:
            out.deadman = section["deadman"]
    _take_periods(section, out, where, problems)
    config_file = section.get("config_file")
    if config_file is not None and not isinstance(config_file, str):
        problems.append(f"{where}.config_file: expected a path, got {config_file!r}")
    elif config_file is not None:
        out.config_file = config_file
    if out.deadman and not out.required:
        problems.append(f"{where}.deadman: needs {where}.required: true (a dead-man that "
                        "may be missing without Zenoh, with only a warning, is none)")
    return out


def _take_names(section: Mapping[str, Any], out: FleetConfig, where: str,
                problems: list[str]) -> None:
    """The prefix (a key expression) and the mode."""
    if "prefix" in section:
        why = key_problem(section["prefix"])
        if why:
            problems.append(f"{where}.prefix: {why}")
        else:
            out.prefix = section["prefix"]
    if "mode" in section:
        if section["mode"] not in MODES:
            problems.append(f"{where}.mode: expected peer or client, got {section['mode']!r}")
        else:
            out.mode = section["mode"]


def _take_endpoints(section: Mapping[str, Any], out: FleetConfig, where: str,
                    problems: list[str]) -> None:
    """connect and listen: one endpoint or a list, added to the base's."""
    for key in ("connect", "listen"):
        value = section.get(key, [])
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list) or not all(isinstance(v, str) and "/" in v
                                                  for v in value):
            problems.append(f"{where}.{key}: expected Zenoh endpoints like "
                            f"tcp/192.168.1.10:7447, got {value!r}")
        else:
            getattr(out, key).extend(value)


def _take_switches(section: Mapping[str, Any], out: FleetConfig, where: str,
                   problems: list[str]) -> None:
    for key in ("multicast", "allow_commands", "required"):
        if key in section:
            if not isinstance(section[key], bool):
                problems.append(f"{where}.{key}: expected true or false, got "
                                f"{section[key]!r}")
            else:
                setattr(out, key, section[key])


def _take_periods(section: Mapping[str, Any], out: FleetConfig, where: str,
                  problems: list[str]) -> None:
    for key, low, high in (("drives_period", 0.05, 60.0), ("alive_timeout", 0.05, 60.0)):
        value = section.get(key, getattr(out, key))
        if not isinstance(value, (int, float)) or isinstance(value, bool) \
                or not low <= value <= high:
            problems.append(f"{where}.{key}: expected seconds {low:g}..{high:g}, got {value!r}")
        else:
            setattr(out, key, float(value))
