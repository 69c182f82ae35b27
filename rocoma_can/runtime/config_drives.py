"""The run config's checks that need its drives, in the order ``config.validate`` runs them:
the drives themselves (each built and planned against its file, then the checks across
them: drivers/plan/drive_clashes.py), the manager's keys that name drives or their COB-IDs,
the controllers' feedback, the URDF's joints and each bus's load.

Each appends "<yaml path>: <what is wrong>" to ``problems`` as config_check.py's do.
"""
from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..drivers.plan.config import LIMIT_KEYS, BusConfig, DriveConfig
from ..drivers.plan.drive_clashes import DriveClash, drive_problems, estop_conflict, node_mismatch
from ..drivers.plan.drive_plan import DrivePlan, pdo_bytes_problem, plan_drive, plan_drives
from ..drivers.plan.pdo_layout import cob_id_clashes
from ..live.urdf import MOVABLE, Robot, UrdfError, read_urdf
from .bus_load import BusLoad, bus_load
from .config_check import unknown_keys

if TYPE_CHECKING:
    from ..plugins import LoadedController  # loaded with the controllers, when checked
    from .config import ManagerNodeConfig  # config.py builds it; these checks fill it in

DEFAULT_BITRATE = 1_000_000  # assumed for the load check when the config gives none
#: interfaces between threads of one process: no wire, no load to check unless the config
#: gives the bit rate of the bus they stand in for (the demo's CAN FD buses)
IN_PROCESS = frozenset({"virtual", "inproc"})
_DRIVE_KEYS = {f.name for f in fields(DriveConfig)}


def check_drive_entries(entries: Any, manager_id: int, base: Path | None, problems: list[str],
                        buses: list[str], named: list[str], fd: Collection[str] = (),
                        period: float | None = None
                        ) -> tuple[list[tuple[DriveConfig, DrivePlan]],
                                   list[tuple[DriveConfig, DrivePlan]]]:
    """Each drive built and measured against its file, with its own plan (two drives of
    one name keep theirs); and those of them whose node id was not already reported, which
    the COB-ID check takes (a taken node id is one problem, not also its PDOs' clashes).
    ``named`` gets every name given, so a drive that failed is not also "no such drive";
    ``fd``: the buses that are CAN FD (the only ones PDOs over 8 bytes go on); ``period``:
    the loop's (s), the limits in time are planned at (None: the rate is wrong, said).
    Every problem is said under its drive, in the order of the list."""
    if not isinstance(entries, list) or not entries:
        problems.append(f"drives: expected a non-empty list of drives, got {entries!r}")
        return [], []
    said: list[list[str]] = [[] for _ in entries]  # each entry's problems
    planned: list[tuple[DriveConfig, DrivePlan]] = []
    place: list[int] = []  # each planned drive's index in the list
    for i, entry in enumerate(entries):
        built = _drive_entry(entry, f"drives[{i}]", base, named, period, said[i])
        if built is not None:
            planned.append(built)
            place.append(i)
    drives = [d for d, _ in planned]
    found: list[list[DriveClash]] = [[] for _ in drives]
    for clash in drive_problems(drives, manager_id, buses):
        found[clash.drive].append(clash)
    clean: list[tuple[DriveConfig, DrivePlan]] = []
    for k, (drive, plan) in enumerate(planned):
        mine, bus = said[place[k]], drive.bus or buses[0]
        mine += [c.at(drives, place) for c in found[k] if c.key != "node_id"]
        why = pdo_bytes_problem(drive, bus, bus in fd) if bus in buses else None
        if why is not None:
            mine.append(f"drives[{place[k]}].pdo_bytes: {why}")
        taken = [c.at(drives, place) for c in found[k] if c.key == "node_id"]
        mine += taken
        if not taken:
            clean.append((drive, plan))
    problems.extend(p for mine in said for p in mine)
    return (_share_nodes(planned, buses, problems, period),
            _share_nodes(clean, buses, [], period))


def _drive_entry(entry: Any, where: str, base: Path | None, named: list[str],
                 period: float | None, problems: list[str]
                 ) -> tuple[DriveConfig, DrivePlan] | None:
    """One entry of ``drives:`` built and planned on its own, or None (said why)."""
    if not isinstance(entry, Mapping):
        problems.append(f"{where}: expected a mapping, got {entry!r}")
        return None
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
    except (ValueError, TypeError) as exc:
        problems.append(f"{where}: {exc}")
        return None
    return plan.drive, plan


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
