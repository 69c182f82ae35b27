"""PDO layouts computed once at start-up from each drive's configured modes and feedback.

The bus budget (docs/configuration.md: bus load) counts every frame a cycle sends, so the
driver maps only the objects the configured modes need and packs them first-fit into PDOs
of ``DriveConfig.pdo_bytes`` (8, CANopen's): a CSP-only drive needs one RPDO (controlword +
mode + target position = 7 bytes); statusword + position + velocity + torque (12 bytes)
needs two TPDOs, statusword + position + torque fits one. A drive on a CAN FD bus that maps
longer PDOs (``pdo_bytes`` up to 64) sends one RPDO and one TPDO instead: each frame costs
its arbitration at the nominal bit rate whatever it carries, so fewer, longer frames fit a
bus at rates where many short ones do not. Each PDO gets a precompiled ``struct.Struct``,
padded to the length a CAN FD frame has on the wire (9 bytes go out as 12: wire.fd_length;
nothing below 9): the cycle never touches canopen's PDO objects.
"""
from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import canopen

from ..files.capabilities import PDO_NOT_VALID, DriveCapabilities, PdoChannel
from ..protocol import cia301, cia402
from ..protocol.wire import fd_length
from .config import FEEDBACK, DriveConfig
from .modes import KIND, DriveMode

PDO_BYTES = 8
PDO_SLOTS = 4


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object: a name the codec uses, where it lives, and its struct format.

    Objects of a drive's fixed mapping that rocoma-can does not command are ``constant``
    entries in RPDOs (sent as the file's value, never as a guess) and named ``IGNORED`` in
    TPDOs (read past)."""
    name: str
    index: int
    subindex: int
    fmt: str  # struct format character, little endian
    constant: int | None = None

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
#: IP: the position target goes to the interpolation data record (the codec's name is the
#: same: controllers write position targets alike for CSP, IP and PP)
IP_TARGET = PdoEntry("target_position", cia402.INTERPOLATION_DATA, 1, "i")
STATUSWORD = PdoEntry("statusword", cia402.STATUSWORD, 0, "H")
POSITION = PdoEntry("position", cia402.POSITION_ACTUAL, 0, "i")
VELOCITY = PdoEntry("velocity", cia402.VELOCITY_ACTUAL, 0, "i")
TORQUE = PdoEntry("torque", cia402.TORQUE_ACTUAL, 0, "h")

TARGET_OF_MODE = {DriveMode.CSP: TARGET_POSITION, DriveMode.IP: IP_TARGET,
                  DriveMode.PP: TARGET_POSITION, DriveMode.CSV: TARGET_VELOCITY,
                  DriveMode.PV: TARGET_VELOCITY, DriveMode.CST: TARGET_TORQUE}
ENTRY_OF_FEEDBACK = {"position": POSITION, "velocity": VELOCITY, "torque": TORQUE}
#: Every name an RPDO codec can be asked to fill, in the order ``LayoutPdo.pack`` takes them
#: (a drive's constant entries follow: ``DriveLayout.rpdo_fields``).
RPDO_FIELDS = ("controlword", "mode", "target_position", "target_velocity", "target_torque")
#: The name of a fixed TPDO's entries that rocoma-can does not read.
IGNORED = "ignored"
_KNOWN = {(e.index, e.subindex): e for e in (CONTROLWORD, MODE, TARGET_POSITION, IP_TARGET,
                                             TARGET_VELOCITY, TARGET_TORQUE, STATUSWORD,
                                             POSITION, VELOCITY, TORQUE)}


@dataclass(frozen=True)
class LayoutPdo:
    """One PDO of one drive: its slot (1..4), COB-ID, mapped entries and codec. ``fixed``:
    the drive's own mapping, used as it is (bring-up writes no mapping for it)."""
    number: int
    cob_id: int
    entries: tuple[PdoEntry, ...]
    codec: struct.Struct = field(compare=False, repr=False)
    fixed: bool = False

    @property
    def size(self) -> int:
        """Bytes of its frame: what is mapped, padded as a CAN FD frame is (``_pdo``)."""
        return self.codec.size

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.entries)

    def positions_in(self, fields: Sequence[str]) -> tuple[int, ...]:
        """Where each mapped entry sits in ``fields`` (for itemgetter-style packing)."""
        return tuple(fields.index(e.name) for e in self.entries)


def first_fit(entries: Iterable[PdoEntry], max_bytes: int = PDO_BYTES,
              limits: Sequence[int] | None = None) -> list[list[PdoEntry]]:
    """Pack entries in order into as few PDOs as first fit allows (order kept within a PDO);
    ``limits``: the most objects each PDO slot takes, in slot order (None: 8 each, as many
    slots as needed). Raises ValueError when the slots cannot take every entry."""
    pdos: list[list[PdoEntry]] = []
    used: list[int] = []
    for e in entries:
        for i, u in enumerate(used):
            limit = 8 if limits is None else limits[i]
            if u + e.size <= max_bytes and len(pdos[i]) < limit:
                pdos[i].append(e)
                used[i] += e.size
                break
        else:
            if limits is not None and len(pdos) >= len(limits):
                raise ValueError("no PDO slot left")
            pdos.append([e])
            used.append(e.size)
    return pdos


def _pdo(number: int, cob_id: int, entries: Sequence[PdoEntry], fixed: bool = False) -> LayoutPdo:
    """The codec pads to the frame's length on the wire (``fd_length``: a 9-byte PDO is a
    12-byte FD frame, and that is what a receiver gets and what the receive check expects)."""
    mapped = sum(e.size for e in entries)
    pad = "x" * (fd_length(mapped) - mapped)
    return LayoutPdo(number, cob_id, tuple(entries),
               struct.Struct("<" + "".join(e.fmt for e in entries) + pad), fixed)


@dataclass(frozen=True)
class DriveLayout:
    """Every PDO one drive exchanges per cycle (bring-up switches the drive's others off)."""
    node_id: int
    rpdos: tuple[LayoutPdo, ...]
    tpdos: tuple[LayoutPdo, ...]

    @property
    def frames_per_cycle(self) -> int:
        return len(self.rpdos) + len(self.tpdos)

    @property
    def constants(self) -> tuple[PdoEntry, ...]:
        return tuple(e for p in self.rpdos for e in p.entries if e.constant is not None)

    @property
    def rpdo_fields(self) -> tuple[str, ...]:
        """RPDO_FIELDS, then the names of this drive's constant entries."""
        return RPDO_FIELDS + tuple(e.name for e in self.constants)

    @property
    def rpdo_constants(self) -> tuple[int, ...]:
        return tuple(int(e.constant or 0) for e in self.constants)

    def maps(self, name: str) -> bool:
        return any(name in p.names for p in (*self.rpdos, *self.tpdos))


def rpdo_entries(modes: Iterable[DriveMode]) -> list[PdoEntry]:
    """Controlword and mode first (they must share the first PDO), then one target per kind
    (position, velocity, torque: config.py allows one mode per kind)."""
    return [CONTROLWORD, MODE] + [TARGET_OF_MODE[m] for m in sorted(set(modes),
                                                                    key=lambda m: KIND[m])]


def tpdo_entries(feedback: Iterable[str] | None) -> list[PdoEntry]:
    return [STATUSWORD] + [ENTRY_OF_FEEDBACK[f] for f in (FEEDBACK if feedback is None
                                                          else feedback)]


def layout_for(drive: DriveConfig, caps: DriveCapabilities | None = None) -> DriveLayout:
    """The PDOs for what the drive's modes and feedback need: mapped first-fit where the
    drive lets us write its mapping, taken as they are where its mapping is fixed. Without
    ``caps``, a drive whose four RPDOs and TPDOs are all remappable (the generic one).
    Raises ValueError saying precisely what the drive cannot carry."""
    rx_need = rpdo_entries(drive.modes)
    tx_need = tpdo_entries(drive.feedback)
    if caps is None:
        rpdos = _remapped(rx_need, _generic(False), drive, "RPDO")
        tpdos = _remapped(tx_need, _generic(True), drive, "TPDO")
        return DriveLayout(drive.node_id, rpdos, tpdos)
    rpdos = _fit(rx_need, caps.rpdos, caps, drive, tx=False)
    tpdos = _fit(tx_need, caps.tpdos, caps, drive, tx=True)
    return DriveLayout(drive.node_id, rpdos, tpdos)


def _generic(tx: bool) -> list[tuple[int, int, int]]:
    """(number, COB-ID base, max objects) of the four remappable PDOs of a generic drive."""
    bases = cia301.TPDO_BASE if tx else cia301.RPDO_BASE
    return [(k + 1, bases[k], 8) for k in range(PDO_SLOTS)]


def _remapped(need: list[PdoEntry], slots: list[tuple[int, int, int]], drive: DriveConfig,
              what: str, node_cob: bool = True) -> tuple[LayoutPdo, ...]:
    """``need`` packed into the remappable ``slots`` (number, COB-ID or base, max objects),
    each slot taking at most its own number of objects."""
    if not need:
        return ()
    slots = [slot for slot in slots if slot[2] > 0]
    try:
        groups = first_fit(need, drive.pdo_bytes, [m for _, _, m in slots])
    except ValueError:
        raise ValueError(f"drive {drive.name!r}: {what} needs more PDOs for "
                         f"{', '.join(e.name for e in need)} than the "
                         f"{len(slots)} it lets us map (at most "
                         f"{', '.join(str(m) for _, _, m in slots) or 'no'} objects each)"
                         ) from None
    return tuple(_pdo(number, cob + (drive.node_id if node_cob else 0), g)
                 for (number, cob, _), g in zip(slots, groups))


#: Objects that move a joint or hold a brake: a fixed RPDO may send them only as 0.
_NEVER_NONZERO = {cia402.TARGET_POSITION, cia402.TARGET_VELOCITY, cia402.TARGET_TORQUE,
                  cia402.VELOCITY_OFFSET, cia402.TORQUE_OFFSET, cia402.INTERPOLATION_DATA,
                  0x60B0, 0x6042, 0x60FE}


def _entry_of(caps: DriveCapabilities, index: int, subindex: int, bits: int, tx: bool,
              drive: DriveConfig, where: str, need: list[PdoEntry]) -> PdoEntry:
    """One entry of a fixed mapping: what the layout needs, else a TPDO entry read past or
    an RPDO constant (the file's value, never a live target of a mode not configured)."""
    known = _KNOWN.get((index, subindex))
    if known is not None and known.size * 8 == bits and known in need:
        return known
    var = caps.variable(index, subindex)
    if var is None or var.data_type is None or len(var) != bits:
        raise ValueError(f"drive {drive.name!r}: {where} maps 0x{index:04X}:{subindex} "
                         f"({bits} bits), which its file does not describe as such")
    struct_type = var.STRUCT_TYPES.get(var.data_type)
    if struct_type is None:  # a string or a domain: no fixed-size number to pack
        raise ValueError(f"drive {drive.name!r}: {where} maps 0x{index:04X}:{subindex}, "
                         "which its file gives a type a PDO cannot carry as a number")
    fmt = struct_type.format.lstrip("<")
    if tx:
        return PdoEntry(IGNORED, index, subindex, fmt)
    value = caps.value(index, subindex)
    constant = int(value) if isinstance(value, int) else 0
    if constant and index in _NEVER_NONZERO:
        raise ValueError(f"drive {drive.name!r}: {where} maps 0x{index:04X}:{subindex}, "
                         f"which rocoma-can does not command here and would send as the "
                         f"file's value {constant} every cycle (a target, offset or output): "
                         "give it 0 in the file")
    return PdoEntry(f"0x{index:04X}:{subindex}", index, subindex, fmt, constant=constant)


def _fit(need: list[PdoEntry], channels: tuple[PdoChannel, ...], caps: DriveCapabilities,
         drive: DriveConfig, tx: bool) -> tuple[LayoutPdo, ...]:
    """Fixed channels that carry something needed are used as they are; what they do not
    carry goes first-fit into the remappable ones; every other channel is switched off."""
    what = "TPDO" if tx else "RPDO"
    bases = cia301.TPDO_BASE if tx else cia301.RPDO_BASE
    used: list[LayoutPdo] = []
    carried: set[str] = set()
    fixed = {ch.number: (ch, [_entry_of(caps, i, s, b, tx, drive, ch.name, need)
                              for i, s, b in _split(ch)])
             for ch in channels if not ch.mapping_writable and ch.mapping}
    while fixed:
        # the fixed channel that adds the most of what is still needed (a drive may offer
        # the controlword in every RPDO: one that adds nothing new is not sent)
        number, (ch, entries) = max(fixed.items(), key=lambda item: (
            len({e.name for e in item[1][1] if e in need} - carried), -item[0]))
        del fixed[number]
        if not {e.name for e in entries if e in need} - carried:
            break
        _check_usable(ch, drive)
        used.append(_pdo(ch.number, _cob_id(ch, bases, drive), entries, fixed=True))
        carried.update(e.name for e in entries if e in need)
    rest = [e for e in need if e.name not in carried]
    if not tx and MODE in rest and ("controlword" in carried
                                    or not caps.carries(cia402.MODES_OF_OPERATION)):
        # the controlword travels in a fixed RPDO without 0x6060, or the file does not let
        # a PDO carry 0x6060: the mode is set once by SDO at bring-up (before enabling), so
        # the drive cannot change mode in the cycle
        rest.remove(MODE)
        if len(drive.modes) > 1:
            raise ValueError(f"drive {drive.name!r}: its fixed RPDO mapping has no 0x6060 "
                             "(modes of operation), so the mode cannot change in the cycle: "
                             f"configure one mode, not {[m.name for m in drive.modes]}")
    free = [ch for ch in channels if ch.mapping_writable and ch.max_objects > 0]
    if rest and not free:
        names = ", ".join(f"{e.name} (0x{e.index:04X})" for e in rest)
        raise ValueError(f"drive {drive.name!r}: its {what} mappings are fixed and none "
                         f"carries {names}; fixed: "
                         + "; ".join(f"{ch.name} = {_describe(ch)}" for ch in channels))
    remapped = _remapped(rest, [(ch.number, _cob_id(ch, bases, drive), ch.max_objects)
                                for ch in free], drive, what, node_cob=False)
    for pdo in remapped:
        _check_usable(next(ch for ch in free if ch.number == pdo.number), drive)
    return tuple(sorted((*used, *remapped), key=lambda p: p.number))


def always_on(layout: DriveLayout, caps: DriveCapabilities) -> list[str]:
    """The drive's PDOs the layout does not use that bring-up cannot switch off (valid, with
    a read-only COB-ID), one sentence each: an RPDO rocoma-can never sends on is inert; a
    TPDO keeps sending, on top of the bus load counted for the layout."""
    notes = []
    for channels, pdos in ((caps.rpdos, layout.rpdos), (caps.tpdos, layout.tpdos)):
        taken = {p.number for p in pdos}
        for ch in channels:
            if ch.number in taken or ch.cob_id & PDO_NOT_VALID or ch.cob_id_writable:
                continue
            what = ("stays on: rocoma-can never sends on it" if not ch.tx else
                    "keeps sending: frames rocoma-can reads past, not counted in the bus "
                    "load")
            notes.append(f"{ch.name} ({_describe(ch)}, COB-ID 0x{ch.cob_id & 0x7FF:03X}, "
                         f"read-only) {what}")
    return notes


def _cob_id(ch: PdoChannel, bases: tuple[int, ...], drive: DriveConfig) -> int:
    """The 11-bit identifier a channel uses: the file's, or the predefined one. A bare base
    (0x180 for TPDO1: "node 0", which does not exist) in a channel whose COB-ID bring-up
    writes means the predefined id: some vendors' EDS files give it without ``$NODEID``.
    A COB-ID the drive does not let us write is taken as the file says."""
    base = bases[ch.number - 1]
    cob = ch.cob_id & 0x7FF
    if cob == 0 or (cob == base and ch.cob_id_writable):
        return base + drive.node_id
    return cob


def _split(ch: PdoChannel) -> list[tuple[int, int, int]]:
    return [(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in ch.mapping]


def _describe(ch: PdoChannel) -> str:
    return ", ".join(f"0x{i:04X}:{s}" for i, s, _ in _split(ch)) or "nothing"


def _check_usable(ch: PdoChannel, drive: DriveConfig) -> None:
    """A channel is usable if it can be made valid and goes every SYNC (an RPDO may also be
    event-driven): where the file fixes its COB-ID or transmission type, it must say so."""
    if ch.cob_id & PDO_NOT_VALID and not ch.cob_id_writable:
        raise ValueError(f"drive {drive.name!r}: {ch.name} is switched off (COB-ID bit 31) "
                         "and its COB-ID cannot be written to switch it on")
    if not ch.transmission_type_writable and ch.transmission_type not in (None, 1) and (
            ch.tx or (ch.transmission_type or 0) <= 240):
        raise ValueError(f"drive {drive.name!r}: {ch.name} has the fixed transmission type "
                         f"{ch.transmission_type}; rocoma-can needs 1 (every SYNC)"
                         + ("" if ch.tx else " or event-driven (254/255)"))


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
                if not var.pdo_mappable and not pdo.fixed:
                    raise ValueError(f"drive {drive!r}: 0x{e.index:04X} ({e.name}) is not "
                                     "PDO-mappable in the EDS")
                if len(var) != e.size * 8:
                    raise ValueError(f"drive {drive!r}: 0x{e.index:04X} ({e.name}) is "
                                     f"{len(var)} bits in the EDS, expected {e.size * 8}")


def cob_id_clashes(drives: Sequence[tuple[DriveConfig, DriveLayout]], manager_node_id: int,
                   estop_cob_id: int = 0, first_bus: str = "",
                   manager_bus: str | None = None) -> list[str]:
    """Every COB-ID that two frames on one bus would share, or that a reserved range holds.

    The predefined connection set (0x180 + node id, ...) cannot clash between nodes with
    distinct ids, but an EDS/DCF may give a PDO an absolute COB-ID: one file for two
    drives, or a DCF for another node id, and drive 1 would take drive 2's targets and
    report its feedback. Checked per bus against the drives' EMCY and PDOs, the manager
    node's EMCY and state frame (on ``manager_bus``; None: on every bus), the e-stop frame
    and the NMT/SYNC/SDO/heartbeat ranges."""
    problems: list[str] = []
    used: dict[str, dict[int, str]] = {}
    node = {cia301.EMCY + manager_node_id: "the manager's EMCY",
            cia301.TPDO_BASE[0] + manager_node_id: "the manager's state frame (TPDO1)"}
    every = {estop_cob_id: "the e-stop frame (manager.estop_cob_id)"} if estop_cob_id else {}
    nodes: set[tuple[str, int, int]] = set()
    distinct = []  # a node id used twice on a bus is its own error (check_drives), not this
    for drive, layout in drives:  # (the axes of a multi-axis node are distinct drives)
        if (drive.bus or first_bus, drive.node_id, drive.axis) not in nodes:
            nodes.add((drive.bus or first_bus, drive.node_id, drive.axis))
            distinct.append((drive, layout))
    for drive, _ in distinct:
        bus = drive.bus or first_bus
        ids = used.setdefault(bus, {**node, **every} if manager_bus in (None, bus)
                              else dict(every))
        ids.setdefault(cia301.EMCY + drive.node_id, f"the EMCY of drive {drive.name!r}")
    for drive, layout in distinct:
        ids = used[drive.bus or first_bus]
        for kind, pdos in (("RPDO", layout.rpdos), ("TPDO", layout.tpdos)):
            for pdo in pdos:
                who = f"{kind}{pdo.number} of drive {drive.name!r}"
                why = cia301.reserved_cob_id(pdo.cob_id)
                other = ids.get(pdo.cob_id)
                if why is not None:
                    problems.append(f"{who}: COB-ID 0x{pdo.cob_id:03X} (from its EDS/DCF) is "
                                    f"{why}")
                elif other is not None:
                    problems.append(f"{who}: COB-ID 0x{pdo.cob_id:03X} (from its EDS/DCF) is "
                                    f"also {other} on the same bus")
                else:
                    ids[pdo.cob_id] = who
    return problems
