"""The run-time configuration (one YAML file) and its validation.

Layout (every key but ``drives`` and ``controllers`` has a default; docs/configuration.md)::

    bus: {interface: socketcan, channel: can0, bitrate: 1000000}
    rate: 500                      # control loop, Hz
    manager:
      node_id: 100                 # the manager's own CANopen node (eds/rocoma_manager.eds)
      heartbeat_ms: 100            # its heartbeat; drives torque-off when it stops
      estop_cob_id: 0x0A0          # any frame with this COB-ID e-stops (0 = off)
      estop_must_be_cleared: true  # every e-stop latches until "clear"
      switch_clients: null         # must stay null: any SDO client may switch (docs/cli.md)
      status_period: 0.1           # s, state TPDO repeat period
      required_drives: null        # drives a switch needs ready (null = all; [] = none)
    realtime: {priority: null, cpus: null,   # SCHED_FIFO priority, CPU list
               spin_us: null}   # spin before each deadline; null: 500, half a period, 100 if RT
    supervision: {tpdo_timeout_cycles: 5, heartbeat_timeout_factor: 2.5,
                  consumer_factor: 2.0, sdo_timeout: 0.5,   # drivers.plan.config.Supervision
                  boot_wait: 1.0, start_timeout: 2.0, reset_timeout: 1.0,
                  enable_timeout: 1.0}                      # start-up (Timeouts)
    timing: {advance: 0.5, initialize_fast: 0.5, overruns: 5, hang: 20}  # in cycles (dt):
                                   # the manager's wall-time supervision of controllers
    zenoh: {prefix: rocoma/<host>, mode: null, connect: [], listen: [], multicast: null,
            allow_commands: false, deadman: null, required: true}  # optional (fleet/config.py);
                                   # null mode/multicast: Zenoh's own (peer, scouting on)
    ros2: {node: rocoma, namespace: /, domain_id: 0, distro: jazzy}  # optional: the manager
                                   # as a ROS 2 node over rmw_zenoh (ros2/config.py)
    urdf: robot.urdf               # optional: the robot Foxglove's 3D panel draws (relative
                                   # to this file; a joint per drive, by the drive's name)
    drives: [ {name, node_id, increments_per_rev, rated_torque_nm, modes, ...} ]
    controllers: [ ... ]           # rocoma_can.plugins format
    emergency_controllers: [ ... ]

``validate`` collects every problem, each as "<yaml path>: <what is wrong>", so one run of
``rocoma-can check-config`` lists them all. The bus load of one cycle (drive PDOs with the
layouts the driver will use, plus SYNC, with worst-case bit stuffing) must fit the bitrate.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ..drivers.plan.config import BusConfig, DriveConfig, Supervision
from ..drivers.plan.drive_plan import DrivePlan
from ..errors import ConfigError
from ..fleet.config import FleetConfig, parse_fleet
from ..live.urdf import Robot
from ..manager_timing import TimingSupervision
from ..ros2.config import Ros2Config, parse_ros2
from ..user_files import yaml_problem
from .bus_load import BusLoad
from .config_check import (
    check_buses,
    check_manager,
    check_rate,
    check_realtime,
    check_regular,
    check_supervision,
    check_timing,
    section_at,
    unknown_keys,
)
from .config_drives import (
    check_bus_loads,
    check_controller_sections,
    check_drive_entries,
    check_manager_and_drives,
    check_urdf,
)

_TOP_KEYS = {"bus", "buses", "rate", "manager", "realtime", "supervision", "timing", "drives",
             "controllers", "emergency_controllers", "zenoh", "urdf", "ros2"}


@dataclass
class ManagerNodeConfig:
    node_id: int = 100
    heartbeat_ms: int = 100
    estop_cob_id: int = 0x0A0
    estop_must_be_cleared: bool = True
    status_period: float = 0.1
    # names of the drives a switch into a controller needs ready (None: every drive)
    required_drives: list[str] | None = None
    bus: str = ""  # the bus its SDO services are on ("" = the first bus)


@dataclass
class RuntimeConfig:
    buses: list[BusConfig]
    rate: float
    manager: ManagerNodeConfig
    drives: list[DriveConfig]
    controllers: dict[str, Any]  # {"controllers": [...], "emergency_controllers": [...]}
    priority: int | None = None
    cpus: set[int] | None = None
    supervision: Supervision = field(default_factory=Supervision)
    timing: TimingSupervision = field(default_factory=TimingSupervision)
    source: str = "<memory>"
    loads: dict[str, BusLoad] = field(default_factory=dict)  # per bus, none on in-process buses
    plans: dict[str, DrivePlan] = field(default_factory=dict)  # per drive name
    fleet: FleetConfig | None = None  # the zenoh: section (None: no Zenoh)
    spin: float | None = None  # s the loop spins before each deadline (None: loop.py's)
    notes: list[str] = field(default_factory=list)  # worth saying, not wrong (check-config)
    robot: Robot | None = None  # urdf: (the live view's 3D robot)
    ros2: Ros2Config | None = None  # the ros2: section (None: no ROS 2 node)

    @property
    def bus(self) -> BusConfig:
        """The first bus: the only one of a single-bus config."""
        return self.buses[0]

    @property
    def node_bus(self) -> BusConfig:
        """The bus the manager's CANopen node serves on (``manager.bus``)."""
        return next((b for b in self.buses if b.label == self.manager.bus), self.buses[0])

    def drives_on(self, bus: BusConfig) -> list[DriveConfig]:
        first = self.buses[0].label
        return [d for d in self.drives if (d.bus or first) == bus.label]

    @property
    def dt(self) -> float:
        return 1.0 / self.rate


# -- loading and validation ---------------------------------------------------------------------

#: A config is a page of YAML: these bound what a hostile or broken file can cost to read.
MAX_CONFIG_BYTES = 1 << 20
MAX_CONFIG_NODES = 100_000  # YAML nodes after expanding aliases ("billion laughs": 10^9)


def load(path: str | Path, rate: float | None = None) -> RuntimeConfig:
    """Read and validate a YAML file; ConfigError lists every problem. ``rate``: instead of
    the file's (``run --rate``), checked with everything that depends on it (the bus load,
    the spin, the cycles of each supervision)."""
    data = _read(path)
    if rate is not None and isinstance(data, Mapping):
        data = {**data, "rate": rate}
    p = Path(path)
    return validate(data, source=str(p), base=p.parent)


@dataclass(frozen=True)
class Reach:
    """How a client reaches the manager a config runs: the bus its node serves on, its node
    id, and the Zenoh prefix the config names (None: it names none; the default is the
    name of the host the manager runs on)."""
    interface: str
    channel: str
    node_id: int
    zenoh_prefix: str | None


def load_reach(path: str | Path) -> Reach:
    """What the operator verbs need of a config (``rocoma-can switch pd -c robot.yaml``):
    its buses, manager and zenoh sections, checked as ``load`` checks them; the rest (the
    drives' files, the controllers' plug-ins, which an operator's machine may not have) is
    not read. ConfigError for a problem in those sections."""
    data = _read(path)
    problems: list[str] = []
    if not isinstance(data, Mapping):
        raise ConfigError([f"{path}: (top): expected a mapping with bus and manager, got "
                           f"{_what(data)}"])
    buses = check_buses(data, problems)
    manager = ManagerNodeConfig()
    m = section_at(data, "manager", problems)
    check_manager(m, manager, problems)
    node_bus = m.get("bus") or buses[0].label
    bus = next((b for b in buses if b.label == node_bus), None)
    if bus is None:
        problems.append(f"manager.bus: expected the name of one of the buses, got {node_bus!r}")
    fleet = parse_fleet(data.get("zenoh"), problems)
    if problems or bus is None:
        raise ConfigError([f"{path}: {p}" for p in problems])
    zenoh = data.get("zenoh")  # a prefix the file names (the default is the robot's host's)
    named = isinstance(zenoh, Mapping) and "prefix" in zenoh and fleet is not None
    return Reach(bus.interface, bus.channel, manager.node_id,
                 fleet.prefix if named and fleet is not None else None)


def _read(path: str | Path) -> Any:
    """A config file's YAML, bounded (MAX_CONFIG_BYTES, MAX_CONFIG_NODES); ConfigError in
    one line for a file that cannot be read or is not YAML."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            raw = f.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError([f"{path}: cannot read: {exc.strerror or exc}"]) from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError([f"{path}: larger than {MAX_CONFIG_BYTES} bytes; not a config file"])
    try:
        text = raw.decode("utf-8")
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        _check_expanded_size(root, str(path))
        _check_keys_once(root, str(path))
        data = yaml.safe_load(text)
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})"]) \
            from None
    except yaml.YAMLError as exc:
        raise ConfigError([yaml_problem(exc, str(path), text)]) from None
    except RecursionError:
        raise ConfigError([f"{path}: nested too deeply; not a config file"]) from None
    return data


def _check_expanded_size(root: yaml.Node | None, source: str) -> None:
    """Refuse a document whose aliases expand to more than MAX_CONFIG_NODES nodes, or that
    refers to itself, before anything walks the expanded data."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(node: yaml.Node) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in active:
            raise ConfigError([f"{source}: a YAML alias refers to itself"])
        active.add(key)
        total = 1
        if isinstance(node, yaml.SequenceNode):
            total += sum(size(child) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            total += sum(size(k) + size(v) for k, v in node.value)
        active.discard(key)
        if total > MAX_CONFIG_NODES:
            raise ConfigError([f"{source}: expands to more than {MAX_CONFIG_NODES} YAML nodes "
                               "(aliases?); not a config file"])
        sizes[key] = total
        return total

    if root is not None:
        size(root)


def _check_keys_once(root: yaml.Node | None, source: str) -> None:
    """Refuse a mapping that gives one key twice: YAML keeps the last and drops the first
    without a word (a section appended with ``cat >>`` that the file already has, two
    ``node_id:`` in one drive), so the values in force would not be the ones a person reads
    first. A merge key (``<<``) is YAML's own way to override, and is left alone."""
    seen: set[int] = set()

    def walk(node: yaml.Node, where: str) -> None:
        if id(node) in seen:  # an alias: walked where it was defined
            return
        seen.add(id(node))
        if isinstance(node, yaml.SequenceNode):
            for k, child in enumerate(node.value):
                walk(child, f"{where}[{k}]")
        elif isinstance(node, yaml.MappingNode):
            first: dict[str, yaml.Node] = {}
            for key, value in node.value:
                name = key.value if isinstance(key, yaml.ScalarNode) else None
                path = f"{where}.{name}" if where else str(name)
                if name is not None and name != "<<":
                    if name in first:
                        mark = key.start_mark
                        raise ConfigError([
                            f"{source}: line {mark.line + 1}, column {mark.column + 1}: "
                            f"{path}: given twice (first on line "
                            f"{first[name].start_mark.line + 1}): YAML keeps only the last; "
                            "give it once"])
                    first[name] = key
                walk(value, path)

    if root is not None:
        walk(root, "")


def _what(data: Any) -> str:
    """What a YAML document is, as a person would say it."""
    if data is None:
        return "an empty file"
    return {list: "a list", str: "a string", int: "an integer", float: "a number",
            bool: "a boolean"}.get(type(data), type(data).__name__)


def validate(data: Any, source: str = "<memory>", base: Path | None = None,
             check_controllers: bool = True) -> RuntimeConfig:
    """Build a RuntimeConfig from a parsed YAML mapping, or raise ConfigError (all problems).
    One check per section (config_check.py, config_drives.py); each appends what is wrong
    with it to ``problems``."""
    problems: list[str] = []
    if not isinstance(data, Mapping):
        raise ConfigError([f"{source}: (top): expected a mapping with bus, rate, drives, "
                           f"controllers, got {_what(data)}"])
    # a misspelt section is read under the name it was meant to have: its own problem is
    # the spelling, not also "no controllers" or "no drives"
    data = unknown_keys(data, _TOP_KEYS, "", problems)
    buses = check_buses(data, problems)
    rate = check_rate(data, problems)
    m = section_at(data, "manager", problems)
    manager = ManagerNodeConfig()
    check_manager(m, manager, problems)
    priority, cpus, spin_us = check_realtime(section_at(data, "realtime", problems), rate,
                                             problems)
    supervision = check_supervision(section_at(data, "supervision", problems), manager,
                                    problems)
    timing = check_timing(section_at(data, "timing", problems), problems)
    named: list[str] = []  # every drive name given, built or not
    planned, clean = check_drive_entries(data.get("drives"), manager.node_id, base,
                                         problems, [b.label for b in buses], named,
                                         fd={b.label for b in buses if b.fd},
                                         period=1.0 / rate if rate is not None else None)
    drives = [d for d, _ in planned]
    plans: dict[str, DrivePlan] = {}
    for d, plan in planned:
        plans.setdefault(d.name, plan)
    check_manager_and_drives(manager, m, buses, drives, clean, named, problems)
    fleet = parse_fleet(data.get("zenoh"), problems)
    if fleet is not None and fleet.config_file and base is not None:
        fleet.config_file = str(base / fleet.config_file)  # relative to the YAML file
    if fleet is not None and fleet.config_file:
        check_regular("zenoh.config_file", fleet.config_file, problems)
    ros2 = parse_ros2(data.get("ros2"), problems)
    controllers = {k: data.get(k) for k in ("controllers", "emergency_controllers")}
    notes = check_controller_sections(controllers, drives, check_controllers, problems)
    robot, urdf_notes = check_urdf(data.get("urdf"), base, drives, problems)
    loads = check_bus_loads(data, buses, planned, rate, problems)
    if problems:
        raise ConfigError([f"{source}: {p}" for p in problems])
    assert rate is not None  # a rate that is wrong is a problem
    return RuntimeConfig(buses, float(rate), manager, drives,
                         controllers, priority, set(cpus) if cpus else None, supervision,
                         timing, source, loads, plans, fleet,
                         spin=None if spin_us is None else spin_us * 1e-6,
                         notes=notes + urdf_notes, robot=robot, ros2=ros2)

