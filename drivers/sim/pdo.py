"""The simulated drive's PDOs: compiled from the OD's communication and mapping objects.

Each of the four RPDOs and four TPDOs is compiled into one struct layout whenever a PDO
object changes or the node starts, so a SYNC packs and unpacks with one struct call per
PDO. Synchronous RPDOs (transmission type 0-240) take effect at the next SYNC; event-driven
ones (254/255) at once. Synchronous TPDOs go out every n-th SYNC (type 1-240) or on SYNC
when changed (type 0); event-driven TPDOs whenever their data changed. PDOs are sent and
received only in OPERATIONAL.
"""
from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from operator import itemgetter
from typing import Any

import can

from .. import cia301 as c301
from ..cia301 import NmtState
from .faults import EmcyProducer, InjectedFaults
from .nmt import NmtSlave
from .objects import CONTROLWORD, MODE, MODE_DISPLAY, PDO_NOT_VALID, Key, ObjectDictionaryServer
from .port import Segment

_OPERATIONAL = NmtState.OPERATIONAL  # a module global: an enum member costs ~100 ns a look-up


@dataclass
class Pdo:
    """One PDO as configured in the OD, compiled for struct packing."""
    number: int
    cob_id: int
    valid: bool
    trans_type: int
    keys: tuple[Key, ...]
    layout: struct.Struct
    values_of: Callable[[dict[Key, Any]], tuple[Any, ...]]
    frame: can.Message             # TPDO: pre-encoded, filled in place before each send
    controlword_at: int | None = None  # RPDO: where the controlword and the mode of
    mode_at: int | None = None         # operation are in ``keys``, if mapped
    counter: int = 0
    last: bytes | None = None      # event-driven TPDO: what was sent last
    pending: bytes | None = None   # synchronous RPDO: received, applied at the next SYNC


class PdoService:
    def __init__(self, node_id: int, segment: Segment, objects: ObjectDictionaryServer,
                 nmt: NmtSlave, emcy: EmcyProducer, faults: InjectedFaults,
                 send: Callable[[int, bytes], None],
                 send_frame: Callable[[can.Message], None],
                 on_controlword: Callable[[int], None]) -> None:
        self._node_id = node_id
        self._seg = segment
        self._objects = objects
        self._values = objects.values
        self._nmt = nmt
        self._emcy = emcy
        self._faults = faults
        self._send = send
        self._send_frame = send_frame
        self._on_controlword = on_controlword
        self._tpdos: list[Pdo] = []
        self._rpdos: list[Pdo] = []
        self._event_tpdos: list[Pdo] = []
        self._sync_tpdos: list[Pdo] = []  # valid, transmission type 0-240

    def build(self) -> None:
        """Compile every PDO from the OD and tell the segment which RPDOs to route here."""
        present = self._values.__contains__  # a drive may have fewer than four of each
        self._rpdos = [self._compile(0x1400 + n, 0x1600 + n, n) for n in range(4)
                       if present((0x1400 + n, 1)) and present((0x1600 + n, 0))]
        self._tpdos = [self._compile(0x1800 + n, 0x1A00 + n, n) for n in range(4)
                       if present((0x1800 + n, 1)) and present((0x1A00 + n, 0))]
        self._event_tpdos = [p for p in self._tpdos if p.valid and p.trans_type >= 254]
        self._sync_tpdos = [p for p in self._tpdos if p.valid and p.trans_type <= 240]
        self._seg.set_rpdo_routes(self._node_id, {
            p.cob_id: partial(self.on_rpdo, p) for p in self._rpdos if p.valid})

    def _compile(self, comm: int, mapping: int, number: int) -> Pdo:
        raw = self._values[(comm, 1)]
        keys: list[Key] = []
        fmt = "<"
        for sub in range(1, self._values[(mapping, 0)] + 1):
            entry = self._values[(mapping, sub)]
            var = self._objects.var(entry >> 16, (entry >> 8) & 0xFF)
            keys.append((var.index, var.subindex))
            assert var.data_type is not None  # mappable objects have one (checked on write)
            fmt += var.STRUCT_TYPES[var.data_type].format.lstrip("<")
        values_of: Callable[[dict[Key, Any]], tuple[Any, ...]]
        if keys:
            values_of = itemgetter(*keys)
            if len(keys) == 1:
                single = values_of
                values_of = lambda values: (single(values),)  # noqa: E731
        else:
            values_of = lambda values: ()  # noqa: E731
        layout = struct.Struct(fmt)
        fd = self._seg.fd
        frame = can.Message(arbitration_id=raw & 0x7FF, data=bytearray(layout.size),
                            is_extended_id=False, is_fd=fd, bitrate_switch=fd)
        return Pdo(number=number, cob_id=raw & 0x7FF, valid=not raw & PDO_NOT_VALID,
                   trans_type=self._values.get((comm, 2), 255), keys=tuple(keys),
                   layout=layout, values_of=values_of, frame=frame,
                   controlword_at=keys.index(CONTROLWORD) if CONTROLWORD in keys else None,
                   mode_at=keys.index(MODE) if MODE in keys else None)

    # ------------------------------------------------------------------ RPDOs
    def on_rpdo(self, pdo: Pdo, data: bytes) -> None:
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

    def _apply(self, pdo: Pdo, data: bytes) -> None:
        """The PDO's objects take their values at once (one dict update: this runs for every
        drive on every SYNC), then what the controlword and the mode make happen."""
        new = pdo.layout.unpack_from(data)
        values = self._values
        mode_at = pdo.mode_at
        if mode_at is not None and new[mode_at] != values[MODE] \
                and not self._objects.mode_supported(new[mode_at]):
            # a real drive ignores an unsupported mode from a PDO; the other objects apply
            values.update((k, v) for k, v in zip(pdo.keys, new) if k != MODE)
            mode_at = None
        else:
            values.update(zip(pdo.keys, new))
        if mode_at is not None:
            values[MODE_DISPLAY] = new[mode_at]
        if pdo.controlword_at is not None:
            self._on_controlword(new[pdo.controlword_at])

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

    def _send_tpdo(self, pdo: Pdo) -> None:
        data = pdo.layout.pack(*pdo.values_of(self._values))
        pdo.last = data
        delay = self._faults.tpdo_delay
        if delay > 0:
            self._seg.schedule(self._seg.clock() + delay, self._send, pdo.cob_id, data)
        else:
            self._send(pdo.cob_id, data)
