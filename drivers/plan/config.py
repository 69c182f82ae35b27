"""What the CAN hardware layer needs to know about each drive, checked once at start-up.

Plain dataclasses so the runtime can build them from YAML (``DriveConfig.from_dict``); every
check raises ValueError naming the drive and the field, because a wrong gear ratio or node id
found at run time is a moving robot doing the wrong thing.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, Literal

from ...user_files import not_regular
from ..files.identity import Identity, identity_from_config
from ..protocol.cia402 import MAX_AXES
from ..protocol.joints import JointMode
from .modes import BY_NAME, KIND, DriveMode


def whole(value: Any) -> bool:
    """An integer, and not a bool (YAML ``true`` is not node 1)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_node_id(value: Any) -> bool:
    """A CANopen node id: a whole number 1..127 (a drive's, the manager's)."""
    return whole(value) and 1 <= value <= 127


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) \
        and math.isfinite(value)


def _positive(where: str, name: str, value: Any) -> None:
    if not _finite(value) or value <= 0:
        raise ValueError(f"{where}: {name} must be a positive number, got {value!r}")


@dataclass(frozen=True)
class BusConfig:
    """Where the drives are: any python-can interface (socketcan, virtual, pcan, ...).

    ``name`` is what drives call their bus (``DriveConfig.bus``); it defaults to the
    channel. ``fd``: CAN FD frames (bit rate switching in the data phase at
    ``data_bitrate``); on socketcan both bit rates are set with ``ip link``, as the
    classic one is.
    """
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int | None = None  # socketcan ignores it: set it with `ip link`
    name: str = ""
    fd: bool = False
    data_bitrate: int | None = None

    def __post_init__(self) -> None:
        where = f"bus {self.label!r}"
        if self.data_bitrate is not None and not self.fd:
            raise ValueError(f"{where}: data_bitrate needs fd: true")
        for name in ("bitrate", "data_bitrate"):
            value = getattr(self, name)
            if value is not None and (not whole(value) or value <= 0):
                raise ValueError(f"{where}: {name} must be a positive integer (bit/s), "
                                 f"got {value!r}")

    @property
    def label(self) -> str:
        return self.name or self.channel


@dataclass(frozen=True)
class Timeouts:
    """Seconds each start-up step may take before the drive is reported FAILED. Wall time:
    give a machine that may stall the process more than its longest stall."""
    boot_wait: float = 1.0   # wait this long for boot-up/heartbeat, then probe by SDO anyway
    start: float = 2.0       # NMT start -> first TPDO
    reset: float = 1.0       # fault reset -> statusword without fault
    enable: float = 1.0      # each enable step, seen to operation enabled (enable.py)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not _finite(value) or value < 0:
                raise ValueError(f"timeouts.{f.name} must be a number of seconds >= 0, "
                                 f"got {value!r}")


@dataclass(frozen=True)
class Supervision:
    """How the hardware layer judges its drives, and how long it waits for them.

    TPDO supervision counts cycles, so it sleeps through a stalled machine; heartbeat
    deadlines are a factor of each drive's heartbeat period; the drives' consumer of the
    manager's heartbeat is ``consumer_factor`` manager periods (0x1016, written at bring-up).
    """
    tpdo_timeout_cycles: int = 5         # cycles without a drive's TPDOs -> fault
    heartbeat_timeout_factor: float = 2.5  # drive heartbeat periods -> heartbeat lost
    consumer_factor: float = 2.0         # manager heartbeat periods the drives wait
    sdo_timeout: float = 0.5             # s, one SDO answer at start-up and recovery
    sdo_retries: int = 0                 # extra tries of an SDO request that got no answer
    timeouts: Timeouts = Timeouts()

    def __post_init__(self) -> None:
        if not whole(self.tpdo_timeout_cycles) or self.tpdo_timeout_cycles < 1:
            raise ValueError("supervision.tpdo_timeout_cycles must be a whole number >= 1, "
                             f"got {self.tpdo_timeout_cycles!r}")
        for name in ("heartbeat_timeout_factor", "consumer_factor"):
            value = getattr(self, name)
            if not _finite(value) or value <= 1.0:
                raise ValueError(f"supervision.{name} must be > 1 (a deadline shorter than "
                                 f"the heartbeat period always trips), got {value!r}")
        if not _finite(self.sdo_timeout) or self.sdo_timeout <= 0:
            raise ValueError(f"supervision.sdo_timeout must be > 0 s, got {self.sdo_timeout!r}")
        if not whole(self.sdo_retries) or self.sdo_retries < 0:
            raise ValueError("supervision.sdo_retries must be a whole number >= 0, "
                             f"got {self.sdo_retries!r}")

    def consumer_ms(self, manager_heartbeat_ms: int) -> int:
        """The drives' heartbeat consumer time (0x1016) for this manager heartbeat."""
        if not 1 <= manager_heartbeat_ms \
                or self.consumer_overflow(manager_heartbeat_ms) is not None:
            raise ValueError("manager_heartbeat_ms must be >= 1 and its product with "
                             "supervision.consumer_factor <= 65535 ms (the drives' heartbeat "
                             f"consumer time); got {manager_heartbeat_ms} and "
                             f"{self.consumer_factor}")
        return int(round(manager_heartbeat_ms * self.consumer_factor))

    def consumer_overflow(self, manager_heartbeat_ms: int) -> str | None:
        """Why ``consumer_factor`` manager heartbeat periods do not fit the drives'
        heartbeat consumer time (0x1016: 16 bits of ms), or None."""
        consumer_ms = int(round(manager_heartbeat_ms * self.consumer_factor))
        if consumer_ms <= 0xFFFF:
            return None
        return (f"{self.consumer_factor:g} x manager.heartbeat_ms {manager_heartbeat_ms} = "
                f"{consumer_ms} ms, more than the drives' heartbeat consumer (0x1016) can "
                "hold (65535 ms)")


#: Feedback objects a drive can report in its TPDOs (statusword is always mapped).
FEEDBACK = ("position", "velocity", "torque")
_REQUIRED = ("name", "node_id", "increments_per_rev", "rated_torque_nm")
_MODE_NAMES = ", ".join(BY_NAME)


def _mode(value: Any, where: str) -> DriveMode:
    """A mode by config name (csp, ip, pv, ...) or by its 0x6060 number."""
    if isinstance(value, str) and value.strip().lower() in BY_NAME:
        return BY_NAME[value.strip().lower()]
    if whole(value) and value in {int(m) for m in DriveMode}:
        return DriveMode(value)
    raise ValueError(f"{where}: unknown mode {value!r}; use {_MODE_NAMES} (position: csp, ip "
                     "or pp; velocity: csv or pv; torque: cst)")


def _modes(given: Any, where: str) -> tuple[DriveMode, ...]:
    """``modes:`` (YAML: a name, a number or a list of them) as distinct modes, at most one
    of each kind: a controller's target of one kind goes in one mode."""
    modes = (given,) if isinstance(given, (str, int)) else tuple(given)
    if not modes:
        raise ValueError(f"{where}: modes must name at least one of {_MODE_NAMES}")
    out = tuple(dict.fromkeys(_mode(m, f"{where}: modes") for m in modes))
    kinds: dict[JointMode, DriveMode] = {}
    for m in out:
        other = kinds.setdefault(KIND[m], m)
        if other != m:
            raise ValueError(f"{where}: modes {other.name.lower()} and {m.name.lower()} "
                             f"both carry {KIND[m].name} targets: configure one of them")
    return out


def _feedback(named: Any, where: str) -> tuple[str, ...] | None:
    """``feedback:`` (a name or a list) in FEEDBACK's order; None stays None (every one the
    drive's file has)."""
    if named is None:
        return None
    feedback = (named,) if isinstance(named, str) else tuple(named)
    for name in feedback:
        if name not in FEEDBACK:
            raise ValueError(f"{where}: feedback {name!r} unknown; use {list(FEEDBACK)}")
    return tuple(f for f in FEEDBACK if f in feedback)


#: Keys of a drive's ``limits:`` mapping.
LIMIT_KEYS = ("position", "velocity", "torque", "following_error", "following_error_cycles")


@dataclass(frozen=True)
class DriveLimits:
    """A drive's ``limits:`` (joint side, SI; None = not limited): enforced by the manager
    on every command and written to the drive at bring-up where its file has the object
    (drivers/plan/limits.py), so they hold while the manager is gone too. ``following_error``
    (rad) is the window a CSP drive's actual position may lag its target by: the manager
    e-stops after ``following_error_cycles`` cycles beyond it, the drive (0x6065/0x6066)
    faults after twice that."""
    position: tuple[float, float] | None = None  # rad: [min, max]
    velocity: float | None = None                # rad/s, either direction
    torque: float | None = None                  # Nm, either direction
    following_error: float | None = None         # rad
    following_error_cycles: int = 3

    @classmethod
    def from_value(cls, value: Any, where: str) -> DriveLimits:
        """From YAML: a mapping of any subset of LIMIT_KEYS; every value checked, one line."""
        if isinstance(value, DriveLimits):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(f"{where}: limits must be a mapping of {', '.join(LIMIT_KEYS)}, "
                             f"got {value!r}")
        unknown = sorted(str(k) for k in value if k not in LIMIT_KEYS)
        if unknown:
            close = difflib.get_close_matches(unknown[0], LIMIT_KEYS, n=1)
            hint = f", did you mean {close[0]!r}?" if close else ""
            raise ValueError(f"{where}: limits.{unknown[0]} unknown{hint}; use "
                             f"{', '.join(LIMIT_KEYS)}")
        position = value.get("position")
        if position is not None:
            if isinstance(position, (str, bytes)) or not isinstance(position, Sequence) \
                    or len(position) != 2 or not all(_finite(p) for p in position):
                raise ValueError(f"{where}: limits.position must be [min, max] in rad (two "
                                 f"finite numbers), got {position!r}")
            if not position[0] < position[1]:
                raise ValueError(f"{where}: limits.position min ({position[0]}) must be below "
                                 f"max ({position[1]})")
            position = (float(position[0]), float(position[1]))
        for name in ("velocity", "torque", "following_error"):
            if value.get(name) is not None:
                _positive(where, f"limits.{name}", value[name])
        cycles = value.get("following_error_cycles", 3)
        if not whole(cycles) or cycles < 1:
            raise ValueError(f"{where}: limits.following_error_cycles must be a whole number "
                             f">= 1, got {cycles!r}")

        def number(name: str) -> float | None:
            return None if value.get(name) is None else float(value[name])
        return cls(position, number("velocity"), number("torque"), number("following_error"),
                   cycles)

    def given(self) -> list[str]:
        """The limits set, by name (following_error_cycles goes with following_error)."""
        return [name for name in LIMIT_KEYS[:4] if getattr(self, name) is not None]


#: The old per-drive keys a ``limits:`` entry also sets, and what they hold (manager only).
_OLD_LIMIT_KEYS = (("position", ("position_min", "position_max")),
                   ("velocity", ("max_velocity",)), ("torque", ("max_torque_nm",)))
_OLD_DEFAULTS = {"position_min": -math.inf, "position_max": math.inf,
                 "max_velocity": math.inf, "max_torque_nm": math.inf}


#: How the manager and a drive watch each other's life (CiA 301): the drive's heartbeat
#: producer (0x1017), or node guarding (0x100C/0x100D: the manager asks by remote frame,
#: the drive answers and watches the asking), for drives that have no heartbeat.
GUARDING = ("auto", "heartbeat", "node_guarding")


@dataclass
class DriveConfig:
    """One CiA 402 drive driving one joint.

    Units on the bus: position in increments, velocity in increments per second, torque in
    per mille of the motor's rated torque (0x6076). ``gear_ratio`` is motor turns per joint
    turn; a negative ratio flips the joint direction. Joint torque = motor torque x gear ratio.
    """
    name: str
    node_id: int
    increments_per_rev: int
    rated_torque_nm: float
    gear_ratio: float = 1.0
    modes: tuple[DriveMode, ...] = (DriveMode.CSP,)
    feedback: tuple[str, ...] | None = None  # None: every one the drive's file has
    eds: str | None = None                  # path; None = the shipped generic CiA 402 EDS
    max_torque_nm: float = math.inf         # joint side; commands are clipped to it
    max_velocity: float = math.inf          # rad/s, joint side
    position_min: float = -math.inf         # rad, joint side
    position_max: float = math.inf
    limits: DriveLimits = DriveLimits()     # enforced by the manager and, where its file
                                            # has the objects, the drive (limits.py); the
                                            # four keys above are the manager's only
    heartbeat_ms: int = 100                 # the drive's heartbeat period (0x1017), or
                                            # its guard time (0x100C) when node-guarded
    guarding: str = "auto"                  # how the drive's life is watched: heartbeat,
                                            # node_guarding, or auto (heartbeat if it can)
    bus: str = ""                           # its bus's name; "" = the first (or only) bus
    axis: int = 1                           # its axis in a multi-axis node (CiA 402-2):
                                            # objects at + (axis - 1) x 0x800
    pdo_bytes: int = 8                      # the most one of its PDOs carries: 8 (CANopen);
                                            # up to 64 on a CAN FD bus for a drive that maps
                                            # longer PDOs (CANopen FD): fewer frames a cycle
    accept_unsupervised: bool = False       # run a drive that ignores losing the manager
    homing_method: int | None = None        # 0x6098 written at bring-up; None: as commissioned
    homing_timeout: float = 60.0            # s a homing may take (rocoma-can home DRIVE)
    identity: Identity | Literal["any"] | None = None  # 0x1018 bring-up requires (identity.py);
                                            # None: the file's vendor/product, any: none

    def __post_init__(self) -> None:
        """Each field checked (and the ones YAML gives loosely made exact: modes, feedback,
        limits, identity) in the order they are declared: the first problem raises."""
        where = f"drive {self.name!r}"
        self._check_numbers(where)
        self.modes = _modes(self.modes, where)
        self.feedback = _feedback(self.feedback, where)
        self.limits = DriveLimits.from_value(self.limits, where)
        self._take_limits(where)
        self._check_manager_limits(where)
        self._check_node(where)
        self._check_rest(where)

    def _check_numbers(self, where: str) -> None:
        """The name, the node id and the scaling: what every drive must have."""
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"drive name must be a non-empty string, got {self.name!r}")
        if not is_node_id(self.node_id):
            raise ValueError(f"{where}: node_id must be an integer 1..127, got {self.node_id!r}")
        if not whole(self.increments_per_rev) or self.increments_per_rev <= 0:
            raise ValueError(f"{where}: increments_per_rev must be a positive integer, "
                             f"got {self.increments_per_rev!r}")
        _positive(where, "rated_torque_nm", self.rated_torque_nm)
        if not _finite(self.gear_ratio) or self.gear_ratio == 0:
            raise ValueError(f"{where}: gear_ratio must be a non-zero number, "
                             f"got {self.gear_ratio!r}")

    def _check_manager_limits(self, where: str) -> None:
        """The manager's limits (after ``limits:`` set them): numbers, the range the right
        way round and within what the drive's position can hold."""
        for name in ("max_torque_nm", "max_velocity"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or math.isnan(value) or value <= 0:
                raise ValueError(f"{where}: {name} must be > 0 (inf = no limit), got {value!r}")
        for name in ("position_min", "position_max"):
            if not isinstance(getattr(self, name), (int, float)) or math.isnan(getattr(self, name)):
                raise ValueError(f"{where}: {name} must be a number, got {getattr(self, name)!r}")
        if self.position_min >= self.position_max:
            raise ValueError(f"{where}: position_min ({self.position_min}) must be below "
                             f"position_max ({self.position_max})")
        # a joint position the drive's INT32 position (0x6064, 0x607A) cannot hold wraps to
        # the other end of its range: a limit out there guards nothing
        span = ((1 << 31) - 1) * 2.0 * math.pi / (self.increments_per_rev * abs(self.gear_ratio))
        for name in ("position_min", "position_max"):
            value = getattr(self, name)
            if math.isfinite(value) and abs(value) > span:
                said = name if self.limits.position is None \
                    else f"limits.position {name.removeprefix('position_')}"
                raise ValueError(
                    f"{where}: {said} {value:g} rad is beyond what the drive's position "
                    f"(INT32 increments, 0x6064/0x607A) holds at {self.increments_per_rev} "
                    f"increments a turn and gear ratio {self.gear_ratio:g}: +-{span:.4g} rad")

    def _check_node(self, where: str) -> None:
        """What the drive's node is on the bus: its heartbeat, axis, PDO size, guarding."""
        if not whole(self.heartbeat_ms) or not 1 <= self.heartbeat_ms <= 0xFFFF:
            raise ValueError(f"{where}: heartbeat_ms must be an integer 1..65535, "
                             f"got {self.heartbeat_ms!r}")
        if not whole(self.axis) or not 1 <= self.axis <= MAX_AXES:
            raise ValueError(f"{where}: axis must be an integer 1..{MAX_AXES} (CiA 402-2), "
                             f"got {self.axis!r}")
        if not whole(self.pdo_bytes) or not 8 <= self.pdo_bytes <= 64:
            raise ValueError(f"{where}: pdo_bytes must be an integer 8..64 (bytes per PDO; "
                             f"over 8 on a CAN FD bus only), got {self.pdo_bytes!r}")
        if self.guarding not in GUARDING:
            raise ValueError(f"{where}: guarding must be one of {list(GUARDING)}, "
                             f"got {self.guarding!r}")

    def _check_rest(self, where: str) -> None:
        """Homing, the manager-loss waiver, the bus's name, the identity and the file."""
        if self.homing_method is not None and (not whole(self.homing_method)
                                               or not -128 <= self.homing_method <= 127):
            raise ValueError(f"{where}: homing_method must be a CiA 402 method number "
                             f"(0x6098, -128..127), got {self.homing_method!r}")
        _positive(where, "homing_timeout", self.homing_timeout)
        if not isinstance(self.accept_unsupervised, bool):
            raise ValueError(f"{where}: accept_unsupervised must be true or false, "
                             f"got {self.accept_unsupervised!r}")
        if not isinstance(self.bus, str):
            raise ValueError(f"{where}: bus must be the name of a bus, got {self.bus!r}")
        self.identity = identity_from_config(self.identity, where)
        wrong = not_regular(self.eds) if self.eds is not None else None
        if wrong is not None:  # (a FIFO would hang reading it: user_files.py)
            raise ValueError(f"{where}: eds file {self.eds!r}{wrong}")

    def _take_limits(self, where: str) -> None:
        """``limits:`` sets the manager's limits too (one set of numbers for both); an old
        key (position_min, ..., manager only) that says otherwise is an error, not a
        choice made silently."""
        for name, keys in _OLD_LIMIT_KEYS:
            value = getattr(self.limits, name)
            if value is None:
                continue
            values = value if isinstance(value, tuple) else (value,)
            for key, new in zip(keys, values):
                old = getattr(self, key)
                if old != _OLD_DEFAULTS[key] and old != new:
                    raise ValueError(f"{where}: {key} = {old} and limits.{name} = {value} "
                                     f"disagree; keep limits.{name} ({key} is the old, "
                                     "manager-only key)")
                setattr(self, key, new)

    def manager_only_limits(self) -> list[str]:
        """The old keys set without ``limits:`` behind them: the manager enforces them, the
        drive is never told (what they always did)."""
        return [key for name, keys in _OLD_LIMIT_KEYS for key in keys
                if getattr(self.limits, name) is None and getattr(self, key) != _OLD_DEFAULTS[key]]

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DriveConfig:
        """Build from a YAML mapping; unknown keys are an error (a typo must not be ignored)."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known, key=str)
        if unknown:
            close = difflib.get_close_matches(str(unknown[0]), known, n=1)
            hint = f", did you mean {close[0]!r}?" if len(unknown) == 1 and close else ""
            raise ValueError(f"drive {data.get('name', '?')!r}: unknown keys {unknown}{hint}; "
                             f"known keys are {sorted(known)}")
        missing = [k for k in _REQUIRED if k not in data]
        if missing:
            raise ValueError(f"drive {data.get('name', '?')!r}: missing keys {missing}")
        return cls(**dict(data))
