"""The simulated drive's PDOs: compiled from the OD's communication and mapping objects.

Each of the four RPDOs and four TPDOs is compiled into one struct layout whenever a PDO
object changes or the node starts, so a SYNC packs and unpacks with one struct call per
PDO. Synchronous RPDOs (transmission type 0-240) take effect at the next SYNC; event-driven
ones (254/255) at once. Synchronous TPDOs go out every n-th SYNC (type 1-240) or on SYNC
when changed (type 0); event-driven TPDOs whenever their data changed. PDOs are sent and
received only in OPERATIONAL.

The PDOs are the node's, shared by its axes (CiA 402-2): a PDO maps objects of any axis, and
an RPDO's controlword or mode of operation takes effect on the axis whose object it is.
"""
from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import can

from ..protocol import cia301 as c301
from ..protocol.cia301 import NmtState, ObjectKey
from ..protocol.wire import fd_length, picker
from .faults import EmcyProducer, InjectedFaults
from .nmt import NmtSlave
from .objects import PDO_NOT_VALID, AxisKeys, ObjectDictionaryServer
from .port import Segment

_OPERATIONAL = NmtState.OPERATIONAL  # a module global: an enum member's look-up costs more


@dataclass
class ConfiguredPdo:
    """One PDO as configured in the OD, compiled for struct packing."""
    number: int
    cob_id: int
    valid: bool
    trans_type: int
    keys: tuple[ObjectKey, ...]
    layout: struct.Struct
    values_of: Callable[[dict[ObjectKey, Any]], tuple[Any, ...]]
    frame: can.Message             # TPDO: pre-encoded, filled in place before each send
    # RPDO: where in ``keys`` an axis's controlword is, with what it does; where an axis's
    # mode of operation is, with the axis's objects (each empty if none is mapped)
    controlwords: tuple[tuple[int, Callable[[int], None]], ...] = ()
    modes: tuple[tuple[int, AxisKeys], ...] = ()
    counter: int = 0
    last: bytes | None = None      # event-driven TPDO: what was sent last
    pending: bytes | None = None   # synchronous RPDO: received, applied at the next SYNC


class PdoService:
    """The node's PDOs. ``axes``: each axis's objects and what a controlword written to
    it does (its state machine's ``on_controlword``)."""

    def __init__(self, node_id: int, segment: Segment, objects: ObjectDictionaryServer,
                 nmt: NmtSlave, emcy: EmcyProducer, faults: InjectedFaults,
                 send: Callable[[int, bytes], None],
                 send_frame: Callable[[can.Message], None],
                 axes: Sequence[tuple[AxisKeys, Callable[[int], None]]]) -> None:
        self._node_id = node_id
        self._seg = segment
        self._objects = objects
        self._values = objects.values
        self._nmt = nmt
        self._emcy = emcy
        self._faults = faults
        self._send = send
        self._send_frame = send_frame
        self._controlword_of = {keys.controlword: on_cw for keys, on_cw in axes}
        self._axis_of_mode = {keys.mode: keys for keys, _ in axes}
        self._rx: dict[int, ConfiguredPdo] = {}  # PDO number (0-3) -> compiled
        self._tx: dict[int, ConfiguredPdo] = {}
        self._rpdos: list[ConfiguredPdo] = []
        self._event_tpdos: list[ConfiguredPdo] = []
        self._sync_tpdos: list[ConfiguredPdo] = []  # valid, transmission type 0-240

    def build(self) -> None:
        """Compile every PDO from the OD and tell the segment which RPDOs to route here."""
        self._rx = {n: self._compile(0x1400 + n, 0x1600 + n, n) for n in range(4)
                    if self._configured(0x1400 + n)}
        self._tx = {n: self._compile(0x1800 + n, 0x1A00 + n, n) for n in range(4)
                    if self._configured(0x1800 + n)}
        self._derive(routes=True)

    def rebuild(self, index: int) -> None:
        """PDO object ``index`` was written: compile that one PDO again. A master maps a
        PDO entry by entry, an SDO each; compiling all eight each time cost several times
        compiling one, which a lockstep simulator spends in the loop's pass during
        bring-up. The other PDOs keep their state (a TPDO's SYNC count, an RPDO waiting
        for the next SYNC). An index of no PDO here (the drive has four of each) is none."""
        base = next((b for b in (0x1400, 0x1600, 0x1800, 0x1A00) if b <= index < b + 4), None)
        if base is None:
            return
        number = index - base
        receive = base < 0x1800
        comm = (0x1400 if receive else 0x1800) + number
        table = self._rx if receive else self._tx
        if self._configured(comm):
            table[number] = self._compile(comm, comm + 0x200, number)
        else:
            table.pop(number, None)
        self._derive(routes=receive)

    def _configured(self, comm: int) -> bool:
        """The PDO's communication and mapping objects exist (a drive may have fewer than
        four of each)."""
        return (comm, 1) in self._values and (comm + 0x200, 0) in self._values

    def _derive(self, routes: bool) -> None:
        """The lists the cycle walks, in PDO order; the segment's RPDO routes if asked."""
        self._rpdos = [self._rx[n] for n in sorted(self._rx)]
        tpdos = [self._tx[n] for n in sorted(self._tx)]
        self._event_tpdos = [p for p in tpdos if p.valid and p.trans_type >= 254]
        self._sync_tpdos = [p for p in tpdos if p.valid and p.trans_type <= 240]
        if routes:
            self._seg.set_rpdo_routes(self._node_id, {
                p.cob_id: partial(self.on_rpdo, p) for p in self._rpdos if p.valid})

    def _compile(self, comm: int, mapping: int, number: int) -> ConfiguredPdo:
        raw = self._values[(comm, 1)]
        keys: list[ObjectKey] = []
        fmt = "<"
        for sub in range(1, self._values[(mapping, 0)] + 1):
            entry = self._values[(mapping, sub)]
            var = self._objects.var(entry >> 16, (entry >> 8) & 0xFF)
            keys.append((var.index, var.subindex))
            assert var.data_type is not None  # mappable objects have one (checked on write)
            fmt += var.STRUCT_TYPES[var.data_type].format.lstrip("<")
        values_of = picker(keys)
        fd = self._seg.fd
        if fd:  # the frame's length on the wire: a 9-byte mapping goes out (and in) as 12
            mapped = struct.calcsize(fmt)
            fmt += "x" * (fd_length(mapped) - mapped)
        layout = struct.Struct(fmt)
        frame = can.Message(arbitration_id=raw & 0x7FF, data=bytearray(layout.size),
                            is_extended_id=False, is_fd=fd, bitrate_switch=fd)
        return ConfiguredPdo(number=number, cob_id=raw & 0x7FF, valid=not raw & PDO_NOT_VALID,
                   trans_type=self._values.get((comm, 2), 255), keys=tuple(keys),
                   layout=layout, values_of=values_of, frame=frame,
                   controlwords=tuple((at, self._controlword_of[key])
                                      for at, key in enumerate(keys)
                                      if key in self._controlword_of),
                   modes=tuple((at, self._axis_of_mode[key]) for at, key in enumerate(keys)
                               if key in self._axis_of_mode))

    # ------------------------------------------------------------------ RPDOs
    def on_rpdo(self, pdo: ConfiguredPdo, data: bytes) -> None:
        if self._nmt.state != _OPERATIONAL:
            return
        if len(data) < pdo.layout.size:
            self._emcy.emit(c301.EMCY_PDO_LENGTH)
            return
        if pdo.trans_type <= 240:
            pdo.pending = bytes(data)  # synchronous: takes effect at the next SYNC
            return
        self._apply(pdo, data)
        self.emit_event_tpdos()

    def apply_synchronous(self) -> None:
        """On SYNC: the synchronous RPDOs received since the last one take effect."""
        for pdo in self._rpdos:
            if pdo.pending is not None:
                data, pdo.pending = pdo.pending, None
                self._apply(pdo, data)

    def _apply(self, pdo: ConfiguredPdo, data: bytes) -> None:
        """The PDO's objects take their values at once (one dict update: this runs for every
        drive on every SYNC), then what the modes and the controlwords make happen."""
        new = pdo.layout.unpack_from(data)
        values = self._values
        for at, axis in pdo.modes:  # (a display is read-only: never one of ``keys``)
            mode = new[at]
            if mode != values[axis.mode] and not self._objects.mode_supported(mode, axis):
                self._apply_refusing_modes(pdo, new)
                return
            values[axis.mode_display] = mode
        values.update(zip(pdo.keys, new))
        for at, on_controlword in pdo.controlwords:
            on_controlword(new[at])

    def _apply_refusing_modes(self, pdo: ConfiguredPdo, new: tuple[Any, ...]) -> None:
        """``_apply`` of an RPDO with a mode the axis does not support: a real drive ignores
        that mode; the other objects apply."""
        values = self._values
        refused = {axis.mode for at, axis in pdo.modes if new[at] != values[axis.mode]
                   and not self._objects.mode_supported(new[at], axis)}
        values.update((k, v) for k, v in zip(pdo.keys, new) if k not in refused)
        for at, axis in pdo.modes:
            if axis.mode not in refused:
                values[axis.mode_display] = new[at]
        for at, on_controlword in pdo.controlwords:
            on_controlword(new[at])

    # ------------------------------------------------------------------ TPDOs
    def send_synchronous(self) -> None:
        """On SYNC: the synchronous TPDOs that are due, packed into their pre-encoded
        frames (no frame is built per SYNC)."""
        values = self._values
        for pdo in self._sync_tpdos:
            if pdo.trans_type == 0:  # acyclic synchronous: on SYNC, when changed
                if pdo.layout.pack(*pdo.values_of(values)) != pdo.last:
                    self._send_tpdo(pdo)
                continue
            pdo.counter += 1
            if pdo.counter >= pdo.trans_type:
                pdo.counter = 0
                if self._faults.tpdo_delay > 0:  # sent later: the frame would change
                    self._send_tpdo(pdo)
                    continue
                pdo.layout.pack_into(pdo.frame.data, 0, *pdo.values_of(values))
                self._send_frame(pdo.frame)

    def emit_event_tpdos(self) -> None:
        """Event-driven TPDOs whose data changed (called after anything that may change it)."""
        if not self._event_tpdos or self._nmt.state != _OPERATIONAL:
            return
        for pdo in self._event_tpdos:
            if pdo.layout.pack(*pdo.values_of(self._values)) != pdo.last:
                self._send_tpdo(pdo)

    def _send_tpdo(self, pdo: ConfiguredPdo) -> None:
        data = pdo.layout.pack(*pdo.values_of(self._values))
        pdo.last = data
        delay = self._faults.tpdo_delay
        if delay > 0:
            self._seg.schedule(self._seg.clock() + delay, self._send, pdo.cob_id, data)
        else:
            self._send(pdo.cob_id, data)
