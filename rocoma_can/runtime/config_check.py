"""The run config's checks of the sections that stand alone, in the order
``config.validate`` runs them (those that need the drives: config_drives.py).

Each takes its section as parsed YAML, appends "<yaml path>: <what is wrong>" to ``problems``
for every problem it finds and returns what it could build anyway, so that one run of
``rocoma-can check-config`` lists every problem, and the checks after a broken section still
run. The ranges live here, the defaults in the dataclasses (config.py, drivers.plan.config).
"""
from __future__ import annotations

import difflib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from ..drivers.link.bus import unknown_interface
from ..drivers.plan.config import BusConfig, Supervision, Timeouts, is_node_id, whole
from ..drivers.protocol.cia301 import reserved_cob_id
from ..drivers.protocol.wire import MAX_DATA_BITRATE
from ..manager_timing import TimingSupervision
from ..user_files import not_regular
from .loop import spin_fits

if TYPE_CHECKING:
    from .config import ManagerNodeConfig  # config.py builds it; these checks fill it in

_BUS_KEYS = {"interface", "channel", "bitrate", "name", "fd", "data_bitrate"}
_MANAGER_KEYS = {"node_id", "bus", "heartbeat_ms", "estop_cob_id", "estop_must_be_cleared",
                 "switch_clients", "status_period", "required_drives"}
_REALTIME_KEYS = {"priority", "cpus", "spin_us"}
#: CPU numbers realtime.cpus may name (the kernel's affinity mask takes no more)
MAX_CPUS = 4096
#: supervision margins: key -> (whole number?, minimum, maximum); drivers.plan.config.Supervision
#: has the defaults
_SUPERVISION = {
    "tpdo_timeout_cycles": (True, 1, 10_000),
    "heartbeat_timeout_factor": (False, 1.5, 100.0),
    "consumer_factor": (False, 1.5, 100.0),
    "sdo_timeout": (False, 0.01, 30.0),
    "enable_timeout": (False, 0.1, 60.0),
    "boot_wait": (False, 0.0, 60.0),
    "start_timeout": (False, 0.1, 60.0),
    "reset_timeout": (False, 0.1, 60.0),
}
#: the manager's wall-time supervision (rocoma_can.TimingSupervision), in cycles (dt):
#: key -> (whole number?, minimum, maximum)
_TIMING = {
    "advance": (False, 0.01, 100_000.0),
    "initialize_fast": (False, 0.01, 100_000.0),
    "overruns": (True, 1, 1000),
    "hang": (False, 2.0, 100_000.0),
}
#: the supervision keys that are start-up timeouts: key -> drivers.plan.config.Timeouts field
TIMEOUT_KEYS = {"boot_wait": "boot_wait", "start_timeout": "start", "reset_timeout": "reset",
                "enable_timeout": "enable"}


def check_buses(data: Mapping[str, Any], problems: list[str]) -> list[BusConfig]:
    """``bus:`` (one bus, every key optional) or ``buses:`` (a list, each with a name)."""
    if "bus" in data and "buses" in data:
        problems.append("bus, buses: give one bus as bus: or several as buses:, not both")
    if "buses" not in data:
        one = _bus(section_at(data, "bus", problems), "bus", problems, named=False)
        return [one] if one is not None else [BusConfig()]
    entries = data["buses"]
    if not isinstance(entries, list) or not entries:
        problems.append(f"buses: expected a non-empty list of buses, got {entries!r}")
        return [BusConfig()]
    buses: list[BusConfig] = []
    seen: dict[str, int] = {}
    wires: dict[tuple[str, str], int] = {}
    for k, entry in enumerate(entries):
        where = f"buses[{k}]"
        if not isinstance(entry, Mapping):
            problems.append(f"{where}: expected a mapping, got {entry!r}")
            continue
        b = _bus(entry, where, problems, named=True)
        if b is None:
            continue
        if b.label in seen:
            problems.append(f"{where}.name: {b.label!r} is already buses[{seen[b.label]}]")
            continue
        wire = (b.interface, b.channel)
        if wire in wires:  # two SYNCs per cycle on one wire, node ids checked per name
            problems.append(f"{where}.channel: {b.interface}:{b.channel} is already "
                            f"buses[{wires[wire]}]: give each bus once")
            continue
        seen[b.label] = k
        wires[wire] = k
        buses.append(b)
    return buses or [BusConfig()]


def _bus(section: Mapping[str, Any], where: str, problems: list[str],
         named: bool) -> BusConfig | None:
    unknown_keys(section, _BUS_KEYS, where, problems)
    before = len(problems)
    interface = section.get("interface", "socketcan")
    channel = section.get("channel", "can0")
    if whole(channel) and channel >= 0:  # `channel: 0` (Kvaser, IXXAT, Vector number
        channel = str(channel)             # theirs): YAML reads an int; a channel is text
    name = section.get("name", "")
    for key, value in (("interface", interface), ("channel", channel)):
        if not isinstance(value, str) or not value:
            problems.append(f"{where}.{key}: expected a non-empty string, got {value!r}")
    unknown = unknown_interface(interface) if isinstance(interface, str) and interface \
        else None
    if unknown:
        problems.append(f"{where}.interface: {unknown}")
    if not isinstance(name, str) or (named and not name):
        problems.append(f"{where}.name: expected the bus's name (drives name it in their "
                        f"bus:), got {name!r}")
    fd = section.get("fd", False)
    if not isinstance(fd, bool):
        problems.append(f"{where}.fd: expected true or false, got {fd!r}")
    rates = {}
    for key, low, high in (("bitrate", 10_000, 1_000_000),
                           ("data_bitrate", 10_000, MAX_DATA_BITRATE)):
        value = section.get(key)
        if value is not None and (not whole(value) or not low <= value <= high):
            problems.append(f"{where}.{key}: expected an integer {low}..{high} bit/s, "
                            f"got {value!r}")
        rates[key] = value
    if rates["data_bitrate"] is not None and fd is not True:
        problems.append(f"{where}.data_bitrate: only for a CAN FD bus (fd: true)")
    if len(problems) > before:
        return None
    return BusConfig(interface, channel, rates["bitrate"], name, fd, rates["data_bitrate"])


#: the fastest loop a config may ask for, Hz
MAX_RATE = 10_000


def check_rate(data: Mapping[str, Any], problems: list[str]) -> float | None:
    rate = data.get("rate", 500)
    if not isinstance(rate, (int, float)) or isinstance(rate, bool) or not 0 < rate <= MAX_RATE:
        problems.append(f"rate: expected a loop rate in Hz, 0 < rate <= {MAX_RATE}, got "
                        f"{rate!r}")
        return None
    return float(rate)


def check_manager(m: Mapping[str, Any], manager: ManagerNodeConfig,
                  problems: list[str]) -> None:
    """The manager's own keys onto ``manager`` (its defaults: config.py builds it, this
    module only checks); its bus and required drives need the drives: later."""
    unknown_keys(m, _MANAGER_KEYS, "manager", problems)
    given = m.get("node_id", manager.node_id)
    if not is_node_id(given):
        problems.append(f"manager.node_id: expected an integer 1..127, got {given!r}")
    else:
        manager.node_id = given
    hb = m.get("heartbeat_ms", manager.heartbeat_ms)
    if not whole(hb) or not 1 <= hb <= 30000:
        problems.append(f"manager.heartbeat_ms: expected an integer 1..30000 ms, got {hb!r}")
    else:
        manager.heartbeat_ms = hb
    cob = m.get("estop_cob_id", manager.estop_cob_id)
    if not whole(cob) or not 0 <= cob <= 0x7FF:
        problems.append(f"manager.estop_cob_id: expected an 11-bit COB-ID 0x001..0x7FF "
                        f"(0 = off), got {cob!r}")
    elif cob and reserved_cob_id(cob):
        problems.append(f"manager.estop_cob_id: 0x{cob:03X} is {reserved_cob_id(cob)}; "
                        "pick e.g. 0x0A0")
        manager.estop_cob_id = 0
    else:
        manager.estop_cob_id = cob
    must_clear = m.get("estop_must_be_cleared", manager.estop_must_be_cleared)
    if not isinstance(must_clear, bool):
        problems.append(f"manager.estop_must_be_cleared: expected true or false, "
                        f"got {must_clear!r}")
    else:
        manager.estop_must_be_cleared = must_clear
    if m.get("switch_clients") is not None:  # refused, not ignored: no false sense of safety
        problems.append("manager.switch_clients: not supported: on the default SDO channel "
                        "CANopen does not identify the client, so switching cannot be limited "
                        "to some nodes (that needs per-client SDO server channels); remove it")
    period = m.get("status_period", manager.status_period)
    if not isinstance(period, (int, float)) or isinstance(period, bool) or not 0.01 <= period <= 10:
        problems.append(f"manager.status_period: expected seconds 0.01..10, got {period!r}")
    else:
        manager.status_period = float(period)


def check_realtime(rt: Mapping[str, Any], rate: float | None, problems: list[str]
              ) -> tuple[int | None, list[int] | None, float | None]:
    """(priority, cpus, spin_us), each None where not given or wrong."""
    unknown_keys(rt, _REALTIME_KEYS, "realtime", problems)
    priority = rt.get("priority")
    if priority is not None and (not whole(priority) or not 1 <= priority <= 99):
        problems.append(f"realtime.priority: expected null or 1..99, got {priority!r}")
        priority = None
    cpus = rt.get("cpus")
    if cpus is not None and (not isinstance(cpus, list) or not cpus
                             or not all(whole(c) and 0 <= c < MAX_CPUS for c in cpus)):
        problems.append(f"realtime.cpus: expected null or a list of CPU numbers "
                        f"0..{MAX_CPUS - 1}, got {cpus!r}")
        cpus = None
    spin_us = rt.get("spin_us")
    if spin_us is not None and (  # the loop's own check, in seconds: no rounding between
            not isinstance(spin_us, (int, float)) or isinstance(spin_us, bool)
            or not (spin_us >= 0 if rate is None else spin_fits(spin_us * 1e-6, rate))):
        period = f" ({1e6 / rate:.1f} µs at the rate)" if rate is not None else ""
        problems.append(f"realtime.spin_us: expected null or µs, 0 <= spin_us < one "
                        f"period{period}, got {spin_us!r}")
        spin_us = None
    return priority, cpus, spin_us


def check_supervision(section: Mapping[str, Any], manager: ManagerNodeConfig,
                      problems: list[str]) -> Supervision:
    margins = _numbers(section, _SUPERVISION, "supervision", problems)
    timeouts = {name: margins.pop(key) for key, name in TIMEOUT_KEYS.items() if key in margins}
    supervision = Supervision(**margins, timeouts=Timeouts(**timeouts))  # ranges checked above
    why = supervision.consumer_overflow(manager.heartbeat_ms)
    if why is not None:  # the hardware would refuse it at run
        problems.append(f"supervision.consumer_factor: {why}")
    return supervision


def check_timing(section: Mapping[str, Any], problems: list[str]) -> TimingSupervision:
    """The manager's budgets, in cycles: those not given keep TimingSupervision's."""
    return TimingSupervision(**_numbers(section, _TIMING, "timing", problems))


def section_at(data: Mapping[str, Any], key: str, problems: list[str]) -> Mapping[str, Any]:
    value = data.get(key)
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        problems.append(f"{key}: expected a mapping, got {value!r}")
        return {}
    return value


def unknown_keys(section: Mapping[str, Any], known: set[str], where: str,
                 problems: list[str], inside: Mapping[str, str] | None = None
                 ) -> dict[str, Any]:
    """A problem per unknown key, with the known key it is closest to; returns the section
    with each such key read as the one it was meant to be where that one is not given
    too, so what follows is checked as intended instead of reporting the key as missing
    (the section is wrong already: the problem stands). ``inside``: keys of a sub-section
    written one level up (a drive's ``following_error_cycles``), each with the sub-section
    it goes in: said so instead."""
    out = {key: value for key, value in section.items() if key in known}
    for key, value in section.items():
        if key not in known and inside is not None and key in inside:
            sub = inside[key]
            problems.append(f"{where}.{key}: unknown key here, it goes in {sub} "
                            f"({sub}: {{{key}: {value}}})")
            continue
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            if not close:  # a word cut short (gear: gear_ratio) is too short to be "close"
                close = [k for k in known if k.startswith(str(key))]
                close = close if len(close) == 1 else []
            hint = f", did you mean {close[0]!r}?" if close else ""
            path = f"{where}.{key}" if where else str(key)
            problems.append(f"{path}: unknown key{hint} (known: {', '.join(sorted(known))})")
            if close and close[0] not in section and close[0] not in out:
                out[close[0]] = value
    return out


def _numbers(section: Mapping[str, Any], spec: Mapping[str, tuple[bool, float, float]],
             where: str, problems: list[str]) -> dict[str, Any]:
    """The numbers given in a section checked against ``spec`` (the rest keep their
    defaults: Supervision's margins, TimingSupervision's budgets)."""
    unknown_keys(section, set(spec), where, problems)
    out: dict[str, Any] = {}
    for key, value in section.items():
        if key not in spec:
            continue
        integer, low, high = spec[key]
        number = whole(value) if integer else (
            isinstance(value, (int, float)) and not isinstance(value, bool))
        if not number or not low <= value <= high:
            kind = "an integer" if integer else "a number"
            problems.append(f"{where}.{key}: expected {kind} {low}..{high}, got {value!r}")
        else:
            out[key] = value
    return out


def check_regular(key: str, path: str, problems: list[str]) -> None:
    """A file the config names that is read later (``zenoh.config_file``): a problem when
    it is missing or not a regular file (a FIFO would hang the reading: user_files.py)."""
    wrong = not_regular(path)
    if wrong is not None:
        problems.append(f"{key}: {path}{wrong}")
