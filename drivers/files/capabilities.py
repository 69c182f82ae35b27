"""What one drive can do, read once from its EDS or DCF: the single answer check-config,
bring-up and the simulator all use.

Vendor files differ from the generic drive rocoma-can ships: 0x6502 lists only some modes,
or is listed without a value, or is missing; 0x6007, 0x608F, 0x6077 may be missing; some
PDO mappings are fixed (read-only mapping objects); COB-IDs are written ``$NODEID+0x180``;
a DCF carries the commissioned values (``ParameterValue``) over the file's defaults.
device_file.py reads the file; this module turns it into facts with the names the rest of
the driver asks about, so that a missing object is a sentence in check-config, not a
KeyError at bring-up. An object the file lists without a value is unknown, never 0: the
drive is asked at start-up (bring-up reads 0x1000, 0x6502 and the factor group first).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import canopen
from canopen import objectdictionary

from rocoma_can import eds as shipped_eds

from ..protocol import cia301, cia402
from ..protocol.cia301 import ObjectKey
from .device_file import DeviceFileError, read_device_file

#: 0x6502 bits (CiA 402): bit n-1 for mode n of 0x6060, except these vendor-neutral ones
MODE_NAMES = {1: "PP", 2: "VL", 3: "PV", 4: "TQ", 6: "HM", 7: "IP", 8: "CSP", 9: "CSV",
              10: "CST"}
NODE_GUARDING = (cia301.GUARD_TIME, cia301.LIFE_TIME_FACTOR)
PDO_NOT_VALID = 0x8000_0000


class CapabilityError(ValueError):
    """The file cannot be read as an EDS/DCF, or is not a drive's."""


def mode_bit(mode: int) -> int:
    """The 0x6502 bit of a 0x6060 mode number (PP 1 -> bit 0 ... CST 10 -> bit 9)."""
    return 1 << (mode - 1)


@dataclass(frozen=True)
class PdoChannel:
    """One RPDO or TPDO of the drive as its file describes it."""
    tx: bool
    number: int                    # 1..4 (the communication object is 0x1400/0x1800 + n-1)
    cob_id: int                    # sub 1 as the file gives it ($NODEID resolved), bit 31 kept
    cob_id_writable: bool
    transmission_type: int | None  # sub 2; None when the file has none
    transmission_type_writable: bool
    mapping_writable: bool         # sub 0 and every entry writable: we may remap it
    max_objects: int               # entries the mapping object has (its highest sub-index)
    mapping: tuple[int, ...]       # mapped entries (index << 16 | sub << 8 | bits), as given

    @property
    def name(self) -> str:
        return f"{'T' if self.tx else 'R'}PDO{self.number}"

    @property
    def communication_index(self) -> int:
        return (cia301.TPDO_COMM if self.tx else cia301.RPDO_COMM) + self.number - 1

    @property
    def mapping_index(self) -> int:
        return (cia301.TPDO_MAP if self.tx else cia301.RPDO_MAP) + self.number - 1

    def maps(self, index: int, subindex: int = 0) -> bool:
        return any(e >> 16 == index and (e >> 8) & 0xFF == subindex for e in self.mapping)


@dataclass(frozen=True)
class DriveCapabilities:
    """Facts of one drive's EDS/DCF for one node id. Build with ``read_capabilities``."""
    source: str
    node_id: int
    object_dictionary: canopen.ObjectDictionary = field(repr=False, compare=False)
    supported_modes: int | None    # 0x6502, None when the file has no such object
    rpdos: tuple[PdoChannel, ...]
    tpdos: tuple[PdoChannel, ...]
    device_type: int | None = None           # 0x1000 (None: not in the file, or no value)
    commissioned_node_id: int | None = None  # a DCF's [DeviceComissioning] NodeID
    #: objects the file lists without a value: the drive's own value is read at start-up
    unknown: frozenset[ObjectKey] = frozenset()
    #: 0x6502 has a value in the file; else ``supported_modes`` comes from the target
    #: objects the file has (``modes_from_targets``) and the drive is asked at start-up
    modes_stated: bool = True
    #: what reading the file had to assume (encoding, duplicate keys, re-derived COB-IDs)
    file_notes: tuple[str, ...] = ()
    #: the axis of a multi-axis device these facts are of; its profile objects appear at
    #: axis 1's indices in ``object_dictionary`` (``_axis_view``)
    axis: int = 1

    # ------------------------------------------------------------------ objects
    def variable(self, index: int, subindex: int = 0) -> objectdictionary.ODVariable | None:
        obj = self.object_dictionary.get(index)
        if obj is None:
            return None
        if isinstance(obj, objectdictionary.ODVariable):
            return obj if subindex == 0 else None
        var = obj.get(subindex) if subindex in obj else None
        return var if isinstance(var, objectdictionary.ODVariable) else None

    def has(self, index: int, subindex: int = 0) -> bool:
        return self.variable(index, subindex) is not None

    def writable(self, index: int, subindex: int = 0) -> bool:
        var = self.variable(index, subindex)
        return var is not None and var.writable

    def value(self, index: int, subindex: int = 0) -> Any:
        """The commissioned value (a DCF's ParameterValue) over the default; None if neither."""
        var = self.variable(index, subindex)
        if var is None:
            return None
        return var.value if var.value is not None else var.default

    def carries(self, index: int, subindex: int = 0) -> bool:
        """An RPDO can bring this object to the drive every cycle: a fixed RPDO maps it, or
        the file marks it PDO-mappable and some RPDO can be remapped."""
        if any(not ch.mapping_writable and ch.maps(index, subindex) for ch in self.rpdos):
            return True
        var = self.variable(index, subindex)
        return var is not None and bool(var.pdo_mappable) \
            and any(ch.mapping_writable and ch.max_objects > 0 for ch in self.rpdos)

    def why_not_carried(self, index: int, subindex: int = 0) -> str:
        """Why ``carries`` is False, as check-config says it."""
        var = self.variable(index, subindex)
        if var is None:
            return f"its file has no 0x{index:04X}:{subindex}"
        if not var.pdo_mappable:
            return (f"its file does not let a PDO carry 0x{index:04X}:{subindex} "
                    "(PDOMapping=0)")
        fixed = "; ".join(f"{ch.name} = " + (", ".join(
            f"0x{e >> 16:04X}:{(e >> 8) & 0xFF}" for e in ch.mapping) or "nothing")
            for ch in self.rpdos)
        return (f"its RPDO mappings are fixed and none carries 0x{index:04X}:{subindex}; "
                f"fixed: {fixed or 'no RPDOs'}")

    # ------------------------------------------------------------------ modes
    def supports(self, mode: int) -> bool:
        """The mode is listed in 0x6502 (or, where the file gives 0x6502 no value, implied
        by its target objects); a file with neither is taken at its word (True)."""
        return self.supported_modes is None or bool(self.supported_modes & mode_bit(mode))

    def usable(self, mode: int) -> bool:
        """Supported, and its target can travel in an RPDO (a mode whose target cannot is
        no use to a cyclic master)."""
        target = TARGET_OF_MODE.get(mode)  # None: a mode without one (homing)
        return self.supports(mode) and (target is None or self.carries(*target))

    @property
    def mode_names(self) -> list[str]:
        if self.supported_modes is None:
            return []
        return [name for mode, name in MODE_NAMES.items()
                if self.supported_modes & mode_bit(mode)]

    def read_from_drive(self) -> list[str]:
        """The objects rocoma-can depends on that the file leaves without a value: read from
        the drive at start-up, before anything depends on them."""
        return [f"0x{index:04X} ({name})" for index, name in _ASKED
                if any(k[0] == index for k in self.unknown)]

    # ------------------------------------------------------------------ supervision
    @property
    def abort_connection(self) -> bool:
        """0x6007 can be set so that losing the manager disables the drive."""
        return self.writable(cia402.ABORT_CONNECTION_OPTION)

    @property
    def heartbeat_consumer(self) -> bool:
        """0x1016:1 is writable: the drive can watch the manager's heartbeat."""
        return self.writable(cia301.CONSUMER_HEARTBEAT_TIME, 1)

    @property
    def error_behaviour(self) -> bool:
        """0x1029:1 is writable: a communication error changes the drive's NMT state."""
        return self.writable(cia301.ERROR_BEHAVIOR, 1)

    @property
    def node_guarding(self) -> bool:
        """0x100C/0x100D are writable: the manager can guard the drive by remote frames,
        and the drive watches the guarding (life guarding)."""
        return all(self.writable(index) for index in NODE_GUARDING)

    def guarded_by_default(self) -> bool:
        """What ``guarding: auto`` picks: node guarding when the drive has no heartbeat
        producer, or has no heartbeat consumer but can be life-guarded (then guarding is the
        only way it watches the manager); otherwise the heartbeat (CiA 301 prefers it: one
        frame per period instead of a request and an answer)."""
        if not self.node_guarding:
            return False
        return not (self.writable(cia301.PRODUCER_HEARTBEAT_TIME) and self.heartbeat_consumer)

    def manager_loss(self, guarded: bool | None = None) -> list[str]:
        """What the drive does when the manager dies or hangs, strongest first ([] = nothing
        the file lets a master configure). ``guarded``: whether the manager drives node
        guarding (None: as ``guarding: auto`` would)."""
        if guarded is None:
            guarded = self.guarded_by_default()
        watchers = [what for what, there in (
            ("heartbeat consumer 0x1016", self.heartbeat_consumer),
            ("life guarding 0x100C/0x100D", guarded and self.node_guarding)) if there]
        if not watchers:
            return []
        watch = " and ".join(watchers)
        if self.abort_connection:
            ways = [f"{watch} -> 0x6007 = 2: disable voltage"]
        else:
            ways = [f"{watch} -> EMCY 0x8130 only (no 0x6007: the drive's CiA 402 reaction "
                    "is its vendor's)"]
        if self.error_behaviour:
            ways.append("0x1029:1 communication error -> leaves OPERATIONAL (no more RPDOs "
                        "applied)")
        return ways

    def supervised(self, guarded: bool | None = None) -> bool:
        """Losing the manager makes the drive stop applying or obeying commands."""
        watched = self.heartbeat_consumer or (
            self.guarded_by_default() if guarded is None else guarded) and self.node_guarding
        return watched and (self.abort_connection or self.error_behaviour)

    # ------------------------------------------------------------------ report
    def report(self, guarded: bool | None = None) -> list[str]:
        """Lines for check-config: what the file offers and what is missing (``guarded``:
        as for ``manager_loss``)."""
        modes = ", ".join(self.mode_names) if self.supported_modes is not None \
            else "no 0x6502 (not stated)"
        if not self.modes_stated and self.supported_modes is not None:
            modes += " (from its target objects; 0x6502 read from the drive)"
        lines = [f"file: {note}" for note in self.file_notes]
        lines.append(f"modes: {modes}")
        unusable = [f"{MODE_NAMES[m]} (0x{t[0]:04X} not PDO-mappable)"
                    for m, t in TARGET_OF_MODE.items()
                    if self.supports(m) and self.supported_modes is not None
                    and not self.usable(m)]
        if unusable:
            lines.append("modes ruled out: " + ", ".join(unusable))
        asked = self.read_from_drive()
        if asked:
            lines.append("read from the drive at start-up (no value in the file): "
                         + ", ".join(asked))
        for what, channels in (("RPDOs", self.rpdos), ("TPDOs", self.tpdos)):
            parts = []
            for ch in channels:
                kind = "remappable" if ch.mapping_writable else "fixed"
                parts.append(f"{ch.name} {kind} (<= {ch.max_objects} objects)")
            lines.append(f"{what}: {', '.join(parts) or 'none'}")
        missing = [f"0x{index:04X} ({name})" for index, name in OPTIONAL_OBJECTS
                   if not self.has(index, 1 if index in _SUB1 else 0)]
        if missing:
            lines.append("missing: " + ", ".join(missing))
        loss = self.manager_loss(guarded)
        lines.append("manager loss: " + ("; ".join(loss) if loss else
                                         "NOTHING (no heartbeat consumer, no life guarding)"))
        return lines


#: Objects rocoma-can uses when a drive has them, with what it does without them.
OPTIONAL_OBJECTS = (
    (cia402.ABORT_CONNECTION_OPTION, "abort connection option"),
    (cia402.POSITION_ENCODER_RESOLUTION, "encoder resolution: scaling from config only"),
    (cia402.GEAR_RATIO, "gear ratio: scaling from config only"),
    (cia402.RATED_TORQUE, "rated torque: scaling from config only"),
    (cia402.TORQUE_ACTUAL, "torque actual: no torque feedback"),
    (cia402.VELOCITY_ACTUAL, "velocity actual: no velocity feedback"),
    (cia402.SUPPORTED_DRIVE_MODES, "supported modes"),
)
_SUB1 = {cia402.POSITION_ENCODER_RESOLUTION, cia402.GEAR_RATIO}
#: Objects bring-up reads from the drive when the file gives them no value.
_ASKED = (
    (cia301.DEVICE_TYPE, "device type"),
    (cia402.SUPPORTED_DRIVE_MODES, "supported modes"),
    (cia402.POSITION_ENCODER_RESOLUTION, "encoder resolution"),
    (cia402.GEAR_RATIO, "gear ratio"),
    (cia402.RATED_TORQUE, "rated torque"),
)
#: Where each mode's cyclic target goes (0x6502 bit order: PP 1 ... CST 10).
TARGET_OF_MODE: dict[int, tuple[int, int]] = {
    1: (cia402.TARGET_POSITION, 0), 3: (cia402.TARGET_VELOCITY, 0),
    7: (cia402.INTERPOLATION_DATA, 1), 8: (cia402.TARGET_POSITION, 0),
    9: (cia402.TARGET_VELOCITY, 0), 10: (cia402.TARGET_TORQUE, 0)}
#: The modes a file's target objects imply where it states no 0x6502 value.
_MODES_OF_TARGET = (
    (cia402.TARGET_POSITION, 0, (1, 8)), (cia402.TARGET_VELOCITY, 0, (3, 9)),
    (cia402.TARGET_TORQUE, 0, (4, 10)), (cia402.INTERPOLATION_DATA, 1, (7,)),
    (cia402.HOMING_METHOD, 0, (6,)))


def modes_from_targets(od: canopen.ObjectDictionary) -> int:
    """0x6502 as the file's target objects imply it: 0x607A -> CSP and PP, 0x60FF -> CSV
    and PV, 0x6071 -> CST and TQ, 0x60C1 -> IP, 0x6098 -> homing."""
    bits = 0
    for index, subindex, modes in _MODES_OF_TARGET:
        if od.get_variable(index, subindex) is not None:
            for mode in modes:
                bits |= mode_bit(mode)
    return bits


def _channels(od: canopen.ObjectDictionary, tx: bool, node_id: int) -> tuple[PdoChannel, ...]:
    comm_base = cia301.TPDO_COMM if tx else cia301.RPDO_COMM
    map_base = cia301.TPDO_MAP if tx else cia301.RPDO_MAP
    cob_base = cia301.TPDO_BASE if tx else cia301.RPDO_BASE
    found = []
    for k in range(4):
        comm, mapping = od.get(comm_base + k), od.get(map_base + k)
        if not isinstance(comm, objectdictionary.ODRecord | objectdictionary.ODArray) \
                or not isinstance(mapping, objectdictionary.ODRecord | objectdictionary.ODArray):
            continue
        entries = [mapping[s] for s in sorted(mapping.subindices) if s > 0]
        count_var = mapping.get(0) if 0 in mapping else None
        count = _value(count_var)
        given = tuple(_value(e) or 0 for e in entries[:count or 0])
        cob_var = comm.get(1) if 1 in comm else None
        cob = _value(cob_var)
        trans = comm.get(2) if 2 in comm else None
        found.append(PdoChannel(
            tx=tx, number=k + 1,
            cob_id=cob if cob is not None else cob_base[k] + node_id,
            cob_id_writable=cob_var is not None and cob_var.writable,
            transmission_type=_value(trans),
            transmission_type_writable=trans is not None and trans.writable,
            # CiA 301: a PDO's mapping changes only while the PDO is invalid, which takes
            # a writable COB-ID; a read-only one leaves the mapping as the drive has it
            mapping_writable=(count_var is not None and count_var.writable
                              and all(e.writable for e in entries)
                              and cob_var is not None and cob_var.writable),
            max_objects=len(entries),
            mapping=tuple(e for e in given if e)))
    return tuple(found)


def _value(var: objectdictionary.ODVariable | None) -> Any:
    if var is None:
        return None
    return var.value if var.value is not None else var.default


def read_capabilities(path: str | None, node_id: int, axis: int = 1) -> DriveCapabilities:
    """Parse an EDS/DCF (None: the shipped generic drive) for one node id and one of its
    axes. Raises CapabilityError naming the file when it is not a readable EDS/DCF (never a
    parser's traceback), or has no such axis."""
    source = path or str(shipped_eds.path(shipped_eds.CIA402_DRIVE))
    try:
        device = read_device_file(source).for_node(node_id)
        od = device.object_dictionary(node_id)
    except DeviceFileError as exc:
        raise CapabilityError(str(exc)) from None
    except Exception as exc:  # canopen's importer on what the reader let through
        raise CapabilityError(f"{source} is not a readable EDS/DCF file "
                              f"({type(exc).__name__}: {str(exc)[:200]})") from None
    unknown = frozenset(device.unknown)
    if axis > 1:
        od, unknown = _axis_view(od, unknown, axis, source)
    modes = od.get(cia402.SUPPORTED_DRIVE_MODES)
    supported = _value(modes) if isinstance(modes, objectdictionary.ODVariable) else None
    stated = isinstance(supported, int)
    if not stated:
        supported = modes_from_targets(od) or None
    device_type = od.get(cia301.DEVICE_TYPE)
    return DriveCapabilities(
        source=source, node_id=node_id, object_dictionary=od,
        supported_modes=supported,
        rpdos=_channels(od, False, node_id), tpdos=_channels(od, True, node_id),
        device_type=_value(device_type) if isinstance(device_type, objectdictionary.ODVariable)
        else None,
        commissioned_node_id=device.commissioned_node_id,
        unknown=unknown, modes_stated=stated,
        file_notes=tuple(device.notes), axis=axis)


_PROFILE = range(0x6000, 0x6000 + cia402.MAX_AXES * cia402.AXIS_STRIDE)


def _axis_view(od: canopen.ObjectDictionary, unknown: frozenset[ObjectKey], axis: int,
               source: str) -> tuple[canopen.ObjectDictionary, frozenset[ObjectKey]]:
    """The dictionary as axis ``axis`` of a multi-axis device sees it: its profile objects
    (at + (axis - 1) x 0x800 in the file) at the indices of axis 1, the other axes' gone,
    the node's own objects (0x1000-0x5FFF) as they are. Everything that plans a drive then
    reads one axis as it reads a single-axis drive; only the SDO traffic and the mapping
    entries of bring-up shift the indices back (bringup/named_sdo.py)."""
    controlword = cia402.on_axis(cia402.CONTROLWORD, axis)
    if controlword not in od:
        raise CapabilityError(f"{source} has no axis {axis}: no 0x{controlword:04X} (axis "
                              f"{axis}'s controlword, 0x6040 + {axis - 1} x 0x800)")
    shift = (axis - 1) * cia402.AXIS_STRIDE
    view = canopen.ObjectDictionary()
    view.bitrate, view.node_id = od.bitrate, od.node_id
    view.device_information = od.device_information
    for index in od:
        obj = od[index]
        if index not in _PROFILE:
            view.add_object(obj)
        elif 0x6000 + shift <= index < 0x6000 + shift + cia402.AXIS_STRIDE:
            moved = copy.copy(obj)
            moved.index = index - shift
            if isinstance(moved, (objectdictionary.ODRecord, objectdictionary.ODArray)):
                subs = list(moved.subindices.values())
                moved.subindices, moved.names = {}, {}
                for sub in subs:
                    var = copy.copy(sub)
                    var.index = moved.index
                    moved.add_member(var)
            view.add_object(moved)
    kept = frozenset((i - shift, sub) if 0x6000 + shift <= i < 0x6000 + shift
                     + cia402.AXIS_STRIDE else (i, sub)
                     for i, sub in unknown if i not in _PROFILE
                     or 0x6000 + shift <= i < 0x6000 + shift + cia402.AXIS_STRIDE)
    return view, kept

