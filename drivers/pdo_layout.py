"""PDO layouts computed once at start-up from each drive's configured modes and feedback.

The bus budget (README, Configuration: bus load) assumes one RPDO and one TPDO
of at most 8 bytes per drive per cycle. So the driver maps only the objects the configured
modes need and packs them first-fit into 8-byte PDOs: a CSP-only drive needs one RPDO
(controlword + mode + target position = 7 bytes); statusword + position + velocity + torque
(12 bytes) needs two TPDOs, statusword + position + torque fits one. Each PDO gets a
precompiled ``struct.Struct``: the cycle never touches canopen's PDO objects.
"""
from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import canopen

from rocoma_can import eds as shipped_eds

from . import cia301, cia402
from .config import DriveConfig
from .joints import JointMode

PDO_BYTES = 8
PDO_SLOTS = 4


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object: a name the codec uses, where it lives, and its struct format."""
    name: str
    index: int
    subindex: int
    fmt: str  # struct format character, little endian

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.fmt)

    @property
    def mapping(self) -> int:
        """The 0x16xx/0x1Axx mapping value: index, subindex, length in bits."""
        return (self.index << 16) | (self.subindex << 8) | (self.size * 8)


CONTROLWORD = PdoEntry("controlword", cia402.CONTROLWORD, 0, "H")
MODE = PdoEntry("mode", cia402.MODES_OF_OPERATION, 0, "b")
TARGET_POSITION = PdoEntry("target_position", cia402.TARGET_POSITION, 0, "i")
TARGET_VELOCITY = PdoEntry("target_velocity", cia402.TARGET_VELOCITY, 0, "i")
TARGET_TORQUE = PdoEntry("target_torque", cia402.TARGET_TORQUE, 0, "h")
STATUSWORD = PdoEntry("statusword", cia402.STATUSWORD, 0, "H")
POSITION = PdoEntry("position", cia402.POSITION_ACTUAL, 0, "i")
VELOCITY = PdoEntry("velocity", cia402.VELOCITY_ACTUAL, 0, "i")
TORQUE = PdoEntry("torque", cia402.TORQUE_ACTUAL, 0, "h")

TARGET_OF_MODE = {JointMode.CSP: TARGET_POSITION, JointMode.CSV: TARGET_VELOCITY,
                  JointMode.CST: TARGET_TORQUE}
ENTRY_OF_FEEDBACK = {"position": POSITION, "velocity": VELOCITY, "torque": TORQUE}
#: Every name an RPDO codec can be asked to fill, in the order ``Pdo.pack`` takes them.
RPDO_FIELDS = ("controlword", "mode", "target_position", "target_velocity", "target_torque")


@dataclass(frozen=True)
class Pdo:
    """One PDO of one drive: its slot (1..4), COB-ID, mapped entries and codec."""
    number: int
    cob_id: int
    entries: tuple[PdoEntry, ...]
    codec: struct.Struct = field(compare=False, repr=False)

    @property
    def size(self) -> int:
        return self.codec.size

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.entries)

    def positions_in(self, fields: Sequence[str]) -> tuple[int, ...]:
        """Where each mapped entry sits in ``fields`` (for itemgetter-style packing)."""
        return tuple(fields.index(e.name) for e in self.entries)


def first_fit(entries: Iterable[PdoEntry], max_bytes: int = PDO_BYTES) -> list[list[PdoEntry]]:
    """Pack entries in order into as few PDOs as first fit allows (order kept within a PDO)."""
    pdos: list[list[PdoEntry]] = []
    used: list[int] = []
    for e in entries:
        for i, u in enumerate(used):
            if u + e.size <= max_bytes:
                pdos[i].append(e)
                used[i] += e.size
                break
        else:
            pdos.append([e])
            used.append(e.size)
    return pdos


def _pdos(groups: list[list[PdoEntry]], bases: tuple[int, ...], node_id: int,
          what: str, drive: str) -> tuple[Pdo, ...]:
    if len(groups) > PDO_SLOTS:
        raise ValueError(f"drive {drive!r}: {what} needs {len(groups)} PDOs, a drive has "
                         f"{PDO_SLOTS}")
    return tuple(Pdo(k + 1, bases[k] + node_id, tuple(g),
                     struct.Struct("<" + "".join(e.fmt for e in g)))
                 for k, g in enumerate(groups))


@dataclass(frozen=True)
class DriveLayout:
    """Every PDO one drive exchanges per cycle."""
    node_id: int
    rpdos: tuple[Pdo, ...]
    tpdos: tuple[Pdo, ...]

    @property
    def frames_per_cycle(self) -> int:
        return len(self.rpdos) + len(self.tpdos)


def rpdo_entries(modes: Iterable[JointMode]) -> list[PdoEntry]:
    """Controlword and mode first (they must share the first PDO), then one target per mode."""
    return [CONTROLWORD, MODE] + [TARGET_OF_MODE[m] for m in sorted(set(modes))]


def tpdo_entries(feedback: Iterable[str]) -> list[PdoEntry]:
    return [STATUSWORD] + [ENTRY_OF_FEEDBACK[f] for f in feedback]


def layout_for(drive: DriveConfig) -> DriveLayout:
    return DriveLayout(
        drive.node_id,
        _pdos(first_fit(rpdo_entries(drive.modes)), cia301.RPDO_BASE, drive.node_id,
              "RPDO", drive.name),
        _pdos(first_fit(tpdo_entries(drive.feedback)), cia301.TPDO_BASE, drive.node_id,
              "TPDO", drive.name),
    )


def check_against_od(layout: DriveLayout, od: canopen.ObjectDictionary, drive: str) -> None:
    """Fail at start-up, naming the object, if the drive's EDS cannot carry this layout."""
    for pdos, comm, what in ((layout.rpdos, cia301.RPDO_COMM, "RPDO"),
                             (layout.tpdos, cia301.TPDO_COMM, "TPDO")):
        for pdo in pdos:
            if comm + pdo.number - 1 not in od:
                raise ValueError(f"drive {drive!r}: EDS has no {what}{pdo.number} "
                                 f"(0x{comm + pdo.number - 1:04X})")
            for e in pdo.entries:
                var = od.get_variable(e.index, e.subindex)
                if var is None:
                    raise ValueError(f"drive {drive!r}: EDS has no object "
                                     f"0x{e.index:04X}:{e.subindex} ({e.name})")
                if not var.pdo_mappable:
                    raise ValueError(f"drive {drive!r}: 0x{e.index:04X} ({e.name}) is not "
                                     "PDO-mappable in the EDS")
                if len(var) != e.size * 8:
                    raise ValueError(f"drive {drive!r}: 0x{e.index:04X} ({e.name}) is "
                                     f"{len(var)} bits in the EDS, expected {e.size * 8}")


def drive_object_dictionary(drive: DriveConfig, layout: DriveLayout) -> canopen.ObjectDictionary:
    """The drive's EDS/DCF (the shipped generic one when none is configured), parsed for its
    node id and checked against the layout: ValueError naming the drive and the file when it
    is not a readable EDS/DCF or cannot carry the layout (never a parser's traceback)."""
    path = drive.eds or str(shipped_eds.path(shipped_eds.CIA402_DRIVE))
    try:
        od = canopen.import_od(path, drive.node_id)
    except Exception as exc:  # configparser, UnicodeDecodeError, ...: a file that is not an EDS
        raise ValueError(f"drive {drive.name!r}: {path} is not a readable EDS/DCF file "
                         f"({type(exc).__name__}: {str(exc)[:200]})") from None
    check_against_od(layout, od, drive.name)
    return od
