"""The run config's checks, one per section, in the order ``config.validate`` runs them.

Each takes its section as parsed YAML, appends "<yaml path>: <what is wrong>" to ``problems``
for every problem it finds and returns what it could build anyway, so that one run of
``rocoma-can check-config`` lists every problem, and the checks after a broken section still
run. The ranges live here, the defaults in the dataclasses (config.py, drivers.plan.config).
"""
from __future__ import annotations

import difflib
from collections.abc import Collection, Mapping
from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..drivers.link.bus import unknown_interface
from ..drivers.plan.config import (
    LIMIT_KEYS,
    BusConfig,
    DriveConfig,
    Supervision,
    Timeouts,
    estop_conflict,
    node_mismatch,
)
from ..drivers.plan.drive_plan import DrivePlan, pdo_bytes_problem, plan_drive, plan_drives
from ..drivers.plan.pdo_layout import cob_id_clashes
from ..drivers.protocol.cia301 import reserved_cob_id
from ..drivers.protocol.wire import MAX_DATA_BITRATE
from ..live.urdf import MOVABLE, Robot, UrdfError, read_urdf
from ..manager import TimingSupervision
from ..user_files import not_regular
from .bus_load import BusLoad, bus_load
from .loop import spin_fits

if TYPE_CHECKING:
    from ..plugins import LoadedController  # loaded with the controllers, when checked
    from .config import ManagerNodeConfig  # config.py builds it; these checks fill it in

DEFAULT_BITRATE = 1_000_000  # assumed for the load check when the config gives none
#: interfaces between threads of one process: no wire, no load to check unless the config
#: gives the bit rate of the bus they stand in for (the demo's CAN FD buses)
IN_PROCESS = frozenset({"virtual", "inproc"})
_BUS_KEYS = {"interface", "channel", "bitrate", "name", "fd", "data_bitrate"}
_MANAGER_KEYS = {"node_id", "bus", "heartbeat_ms", "estop_cob_id", "estop_must_be_cleared",
                 "switch_clients", "status_period", "required_drives"}
_REALTIME_KEYS = {"priority", "cpus", "spin_us"}
#: CPU numbers realtime.cpus may name (the kernel's affinity mask takes no more)
MAX_CPUS = 4096
_DRIVE_KEYS = {f.name for f in fields(DriveConfig)}
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
    if _is_int(channel) and channel >= 0:  # `channel: 0` (Kvaser, IXXAT, Vector number
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
        if value is not None and (not _is_int(value) or not low <= value <= high):
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
    node_id = m.get("node_id", manager.node_id)
    if not _is_int(node_id) or not 1 <= node_id <= 127:
        problems.append(f"manager.node_id: expected an integer 1..127, got {node_id!r}")
    else:
        manager.node_id = node_id
    hb = m.get("heartbeat_ms", manager.heartbeat_ms)
    if not _is_int(hb) or not 1 <= hb <= 30000:
        problems.append(f"manager.heartbeat_ms: expected an integer 1..30000 ms, got {hb!r}")
    else:
        manager.heartbeat_ms = hb
    cob = m.get("estop_cob_id", manager.estop_cob_id)
    if not _is_int(cob) or not 0 <= cob <= 0x7FF:
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
    if priority is not None and (not _is_int(priority) or not 1 <= priority <= 99):
        problems.append(f"realtime.priority: expected null or 1..99, got {priority!r}")
        priority = None
    cpus = rt.get("cpus")
    if cpus is not None and (not isinstance(cpus, list) or not cpus
                             or not all(_is_int(c) and 0 <= c < MAX_CPUS for c in cpus)):
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
    consumer_ms = round(manager.heartbeat_ms * supervision.consumer_factor)
    if consumer_ms > 0xFFFF:  # 0x1016's 16-bit time: the hardware would refuse it at run
        problems.append(f"supervision.consumer_factor: {supervision.consumer_factor:g} x "
                        f"manager.heartbeat_ms {manager.heartbeat_ms} = {consumer_ms} ms, more "
                        "than the drives' heartbeat consumer (0x1016) can hold (65535 ms)")
    return supervision


def check_timing(section: Mapping[str, Any], problems: list[str]) -> TimingSupervision:
    """The manager's budgets, in cycles: those not given keep TimingSupervision's."""
    return TimingSupervision(**_numbers(section, _TIMING, "timing", problems))


def check_drives(entries: Any, manager_id: int, base: Path | None, problems: list[str],
                 buses: list[str], named: list[str], fd: Collection[str] = (),
                 period: float | None = None
            ) -> tuple[list[tuple[DriveConfig, DrivePlan]], list[tuple[DriveConfig, DrivePlan]]]:
    """Each drive built and measured against its file, with its own plan (two drives of
    one name keep theirs); and those of them whose node id was not already reported, which
    the COB-ID check takes (a taken node id is one problem, not also its PDOs' clashes).
    ``named`` gets every name given, so a drive that failed is not also "no such drive";
    ``fd``: the buses that are CAN FD (the only ones PDOs over 8 bytes go on); ``period``:
    the loop's (s), the limits in time are planned at (None: the rate is wrong, said)."""
    if not isinstance(entries, list) or not entries:
        problems.append(f"drives: expected a non-empty list of drives, got {entries!r}")
        return [], []
    planned: list[tuple[DriveConfig, DrivePlan]] = []
    clean: list[tuple[DriveConfig, DrivePlan]] = []
    names: dict[str, int] = {}
    ids: dict[tuple[str, int, int], int] = {}
    for i, entry in enumerate(entries):
        where = f"drives[{i}]"
        if not isinstance(entry, Mapping):
            problems.append(f"{where}: expected a mapping, got {entry!r}")
            continue
        if isinstance(entry.get("name"), str):
            named.append(entry["name"])
        entry = unknown_keys(entry, _DRIVE_KEYS, where, problems,
                             inside=dict.fromkeys(LIMIT_KEYS, "limits"))
        if base is not None and isinstance(entry.get("eds"), str):
            entry["eds"] = str((base / entry["eds"]).resolve()) \
                if not Path(entry["eds"]).is_absolute() else entry["eds"]
        try:
            # measured against its EDS/DCF: modes, feedback (resolved), PDOs, manager loss
            plan = plan_drive(DriveConfig.from_dict(entry), period=period)
            drive = plan.drive
        except (ValueError, TypeError) as exc:
            problems.append(f"{where}: {exc}")
            continue
        if drive.name in names:
            problems.append(f"{where}.name: {drive.name!r} is already drives[{names[drive.name]}]")
        if drive.bus and drive.bus not in buses:
            problems.append(f"{where}.bus: no bus named {drive.bus!r} (buses: "
                            f"{', '.join(repr(b) for b in buses)})")
        bus = drive.bus or buses[0]
        why = pdo_bytes_problem(drive, bus, bus in fd) if bus in buses else None
        if why is not None:
            problems.append(f"{where}.pdo_bytes: {why}")
        taken = (bus, drive.node_id, drive.axis) in ids
        if taken:
            on = f" on bus {bus!r}" if len(buses) > 1 else ""
            axis = f" axis {drive.axis}" if drive.axis > 1 else ""
            problems.append(f"{where}.node_id: {drive.node_id}{axis} is already used by "
                            f"drives[{ids[bus, drive.node_id, drive.axis]}]{on}")
        elif drive.node_id == manager_id:
            taken = True
            problems.append(f"{where}.node_id: {drive.node_id} is the manager's node id "
                            "(manager.node_id)")
        names.setdefault(drive.name, i)
        ids.setdefault((bus, drive.node_id, drive.axis), i)
        planned.append((drive, plan))
        if not taken:
            clean.append((drive, plan))
    return (_share_nodes(planned, buses, problems, period),
            _share_nodes(clean, buses, [], period))


def _share_nodes(drives: list[tuple[DriveConfig, DrivePlan]], buses: list[str],
                 problems: list[str], period: float | None
                 ) -> list[tuple[DriveConfig, DrivePlan]]:
    """The axes of a multi-axis node planned together (they share its PDO channels:
    drive_plan.plan_drives), each problem said once."""
    nodes: dict[tuple[str, int], list[int]] = {}
    for k, (d, _) in enumerate(drives):
        nodes.setdefault((d.bus or buses[0], d.node_id), []).append(k)
    out = list(drives)
    for members in nodes.values():
        if len(members) < 2:
            continue
        axes = [drives[k][0] for k in members]
        why = next((w for w in (node_mismatch(axes[0], d) for d in axes[1:]) if w), None)
        try:
            if why is not None:
                raise ValueError(why)
            shared = plan_drives(axes, buses[0], period=period)
        except ValueError as exc:
            problems.append(f"drives: {exc}")
            continue
        for k, plan in zip(members, shared):
            out[k] = (drives[k][0], plan)
    return out


def check_manager_and_drives(manager: ManagerNodeConfig, m: Mapping[str, Any],
                             buses: list[BusConfig], drives: list[DriveConfig],
                             clean: list[tuple[DriveConfig, DrivePlan]], named: list[str],
                             problems: list[str]) -> None:
    """What the manager's keys say about the drives: the e-stop COB-ID no node uses, no
    frame of two nodes sharing a COB-ID, the node's bus, the drives a switch requires."""
    cob = manager.estop_cob_id
    why = estop_conflict(cob, drives, manager.node_id) if cob else None
    if why is not None:
        problems.append(f"manager.estop_cob_id: 0x{cob:03X} is {why}: an e-stop frame must "
                        "have an identifier no node uses")
    first = buses[0].label if buses else ""
    node_on = m.get("bus") if isinstance(m.get("bus"), str) and m.get("bus") else first
    # drives already reported for their node id are left out: their clashes are that one
    problems.extend(f"drives: {clash}" for clash in cob_id_clashes(
        [(d, plan.layout) for d, plan in clean], manager.node_id,
        cob if isinstance(cob, int) else 0, first, node_on))
    node_bus = m.get("bus", "")
    if not isinstance(node_bus, str) or (node_bus and node_bus not in
                                         [b.label for b in buses]):
        problems.append(f"manager.bus: expected the name of one of the buses "
                        f"({', '.join(repr(b.label) for b in buses)}), got {node_bus!r}")
    else:
        manager.bus = node_bus
    required = m.get("required_drives")
    names = [d.name for d in drives]
    if required is not None:
        if not isinstance(required, list) or not all(isinstance(n, str) for n in required):
            problems.append("manager.required_drives: expected null (every drive) or a list "
                            f"of drive names, got {required!r}")
        else:
            unknown = [n for n in required if n not in named]
            if unknown:
                problems.append(f"manager.required_drives: no drive named "
                                f"{', '.join(map(repr, unknown))} (drives: {', '.join(names)})")
            else:
                manager.required_drives = list(required)


def check_controller_sections(controllers: dict[str, Any], drives: list[DriveConfig],
                              load_plugins: bool, problems: list[str]) -> list[str]:
    """The controllers load (with ``load_plugins``) and get the feedback they need;
    the notes about them (an emergency controller nothing uses)."""
    notes: list[str] = []
    if not controllers["controllers"]:
        problems.append("controllers: at least one controller is needed")
    elif load_plugins:
        from ..errors import PluginError
        from ..plugins import load_config, unused_emergency
        try:
            loaded = load_config(controllers, note_unused=False)
        except PluginError as exc:
            problems.append(str(exc))
        else:
            problems += _feedback_problems(loaded, drives)
            emergency = controllers["emergency_controllers"] or []
            notes += unused_emergency(loaded, [e["name"] for e in emergency])
    return notes


def check_urdf(value: Any, base: Path | None, drives: list[DriveConfig], problems: list[str]
               ) -> tuple[Robot | None, list[str]]:
    """``urdf:``, a path relative to the config file: the robot Foxglove's 3D panel draws,
    and the notes about it. Each drive must name a movable joint of it: a misspelt name
    would show a joint standing still while the drive moves it. A movable joint no drive
    moves is a note (a passive or another controller's joint): the view shows it at its
    origin."""
    if value is None:
        return None, []
    if not isinstance(value, str) or not value:
        problems.append(f"urdf: expected the path of a URDF file, got {value!r}")
        return None, []
    path = Path(value) if base is None or Path(value).is_absolute() else base / value
    try:
        robot = read_urdf(path)
    except UrdfError as exc:
        problems.append(f"urdf: {exc}")
        return None, []
    joints = {j.name: j for j in robot.joints}
    for d in drives:
        joint = joints.get(d.name)
        if joint is None:
            problems.append(f"urdf: {path} has no joint named {d.name!r} (a drive's name); "
                            f"its movable joints: {', '.join(robot.movable) or 'none'}")
        elif joint.kind not in MOVABLE:
            problems.append(f"urdf: {path}: joint {d.name!r} (a drive's name) is "
                            f"{joint.kind}: the view would never move it")
    idle = [name for name in robot.movable if name not in {d.name for d in drives}]
    return robot, [f"urdf: {path}: no drive moves {', '.join(idle)}: shown at the origin"
                   ] if idle else []


def _feedback_problems(loaded: list[LoadedController], drives: list[DriveConfig]) -> list[str]:
    """A controller that needs feedback some drive does not report (its file lacks the
    object, or its config leaves it out) is refused at load, naming both."""
    problems = []
    for item in loaded:
        for controller in (item.controller, item.emergency):
            if controller is None:
                continue
            for needed in sorted(controller.feedback_needed):
                short = [d.name for d in drives if d.feedback is not None
                         and needed not in d.feedback]
                if short:
                    problems.append(f"{item.where}: controller {controller.name!r} needs "
                                    f"{needed} feedback, which drive(s) {', '.join(short)} do "
                                    "not report (check-config --drives says why)")
    return problems


def check_bus_loads(data: Mapping[str, Any], buses: list[BusConfig],
                    planned: list[tuple[DriveConfig, DrivePlan]], rate: float | None,
                    problems: list[str]) -> dict[str, BusLoad]:
    """Each bus's load per cycle at the rate (an in-process bus only with a bitrate)."""
    drives = [d for d, _ in planned]
    loads: dict[str, BusLoad] = {}
    first = buses[0].label if buses else ""
    for k, b in enumerate(buses):
        on = [d for d in drives if (d.bus or first) == b.label]
        if not on or rate is None or (b.interface in IN_PROCESS and b.bitrate is None):
            continue
        bitrate = b.bitrate or DEFAULT_BITRATE
        data_bitrate = (b.data_bitrate or bitrate) if b.fd else None
        loads[b.label] = load_ = bus_load(
            [p.layout for d, p in planned if (d.bus or first) == b.label], float(rate),
            bitrate, data_bitrate)
        if load_.load > 1.0:
            where = f"buses[{k}] ({b.label})" if "buses" in data else "rate"
            assumed = "" if b.bitrate else f" (no bitrate given: {DEFAULT_BITRATE:,} assumed)"
            problems.append(f"{where}: bus overload{assumed}: {load_.explain()}")
    return loads


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
        whole, low, high = spec[key]
        number = _is_int(value) if whole else (
            isinstance(value, (int, float)) and not isinstance(value, bool))
        if not number or not low <= value <= high:
            kind = "an integer" if whole else "a number"
            problems.append(f"{where}.{key}: expected {kind} {low}..{high}, got {value!r}")
        else:
            out[key] = value
    return out


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_regular(key: str, path: str, problems: list[str]) -> None:
    """A file the config names that is read later (``zenoh.config_file``): a problem when
    it is missing or not a regular file (a FIFO would hang the reading: user_files.py)."""
    wrong = not_regular(path)
    if wrong is not None:
        problems.append(f"{key}: {path}{wrong}")
