"""Receive dispatch: every frame the buses' readers queued, by COB-ID, on the cycle thread.

The reader threads (bus.py) only append frames to each bus's deque; ``drain`` empties them
on the cycle thread, so no lock is shared with a slow thread. Per bus, one table lookup per
frame: the e-stop COB-ID first (never taken for anything else), a TPDO (unpacked into the
raw slots of its drive, or counted and reported when its length is not the mapping's), a
heartbeat or guard answer (every axis of the node), an EMCY. Error frames are judged after
the bus's frames: a bus-off is a fault of every drive on it.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from ..link.bus_port import BusPort
from ..link.frame_io import clock_offset, to_monotonic
from ..plan.scaling import Scaling
from ..protocol import cia301, cia402
from ..protocol.joints import JointState
from .drive_table import DriveTable
from .node_guarding import NodeGuarding
from .supervision import Supervisor

#: A TPDO's receive entry: drive index, its bit in the cycle's mask, size, unpack, targets
_TpdoEntry = tuple[int, int, int, Callable[..., tuple[int, ...]], tuple[np.ndarray, ...]]


class BringupSigns(Protocol):
    """What receiving tells a drive's bring-up (drive_bringup.DriveBringup)."""
    alive: bool
    sto_seen: bool


class Receiver:
    """The receive tables of N drives on their buses and the drain that uses them."""

    def __init__(self, table: DriveTable, *, ports: Sequence[BusPort],
                 raw: dict[str, np.ndarray], state: JointState, scaling: Scaling,
                 supervisor: Supervisor, guarding: NodeGuarding,
                 on_estops: Callable[[BusPort, int, int], None],
                 on_bus_off: Callable[[BusPort, str, float], None]) -> None:
        """``raw``: the raw bus values, one slot per drive, that the TPDOs are unpacked
        into; ``on_estops``: e-stop frames on a bus this cycle (their count and COB-ID);
        ``on_bus_off``: a bus failed."""
        n = len(table)
        self.ports, self._state, self._sup = ports, state, supervisor
        self._node = [d.node for d in table]
        self._raw, self._scaling = raw, scaling
        self._guarding, self._on_estops, self._on_bus_off = guarding, on_estops, on_bus_off
        self._bringups: Sequence[BringupSigns] = ()  # attach_bringups (the hardware's start)
        self.estop_cob_id = 0
        self.rx_bad = 0  # TPDOs with a length other than their mapping's (never decoded)
        self.got = np.zeros(n, dtype=np.int64)  # TPDO bits seen this cycle
        # one bit per TPDO slot a drive's layout uses (a fixed mapping may use TPDO3 and 4)
        self.expected = np.array([sum(1 << (p.number - 1) for p in d.layout.tpdos)
                                  for d in table], dtype=np.int64)
        self.complete = np.zeros(n, dtype=bool)  # every TPDO of the drive arrived
        self.hb_state = [-1] * n                 # NMT state of the last heartbeat
        self.hb_time = np.full(n, -math.inf)
        # per drive: its bus's reader had handed over every frame that arrived before this
        # when the cycle began draining (heartbeat deadlines are judged against it)
        self.heard_until = np.full(n, -math.inf)
        self._drives_of_port = [np.array(port.drives, dtype=np.intp) for port in ports]
        self.tpdo_of: list[dict[int, _TpdoEntry]] = [{} for _ in ports]
        for k, port in enumerate(ports):
            for i in port.drives:
                d = table[i]
                for pdo in d.layout.tpdos:
                    self.tpdo_of[k][pdo.cob_id] = (
                        i, 1 << (pdo.number - 1), pdo.size, pdo.codec.unpack_from,
                        tuple(raw[name] for name in pdo.names))
                if d.leads_node:
                    port.heartbeat_of[cia301.HEARTBEAT + d.node_id] = i
                    port.emcy_of[cia301.EMCY + d.node_id] = d.node

    def attach_bringups(self, bringups: Sequence[BringupSigns]) -> None:
        """The drives' bring-ups, once the hardware has started them: a heartbeat marks
        its drive alive, an EMCY STO its STO seen."""
        self._bringups = bringups

    def cob_ids(self, k: int) -> set[int]:
        """What bus k's receiver keeps (the rest is dropped on the reader thread)."""
        port = self.ports[k]
        return set(self.tpdo_of[k]) | set(port.heartbeat_of) | set(port.emcy_of)

    def drain(self, now: float) -> None:
        """Every queued frame of every bus; then ``complete`` says whose TPDOs all came, and
        JointState holds what they carried."""
        sup, got, state = self._sup, self.got, self._state
        got.fill(0)
        stamp = state.stamp
        offset = clock_offset()
        estop, estops = self.estop_cob_id or -1, 0
        for k, port in enumerate(self.ports):
            rx = port.rx
            tpdo_of, heartbeat_of, emcy_of = self.tpdo_of[k], port.heartbeat_of, port.emcy_of
            self.heard_until[self._drives_of_port[k]] = _received_until(port, now)
            while rx:
                msg = rx.popleft()
                cob = msg.arbitration_id
                if cob == estop:
                    estops += 1
                    continue
                t = to_monotonic(offset, msg.timestamp, now)
                entry = tpdo_of.get(cob)
                if entry is not None:
                    i, bit, size, unpack, targets = entry
                    if msg.dlc != size:  # not what we mapped: never decoded, a fault once armed
                        self.rx_bad += 1
                        sup.on_bad_tpdo(i, cob, msg.dlc, size, t)
                        continue
                    for arr, v in zip(targets, unpack(msg.data)):
                        arr[i] = v
                    got[i] |= bit
                    stamp[i] = t
                    continue
                beat = heartbeat_of.get(cob)
                if beat is not None:
                    if msg.dlc >= 1:
                        self._heartbeat(beat, msg.data[0], t)
                    continue
                axes = emcy_of.get(cob)
                if axes is not None and msg.dlc >= 2:
                    self._emcy(axes, msg.data[0] | (msg.data[1] << 8), t)
            if estops:  # one request per bus and cycle, however often a sender repeats
                self._on_estops(port, estops, estop)
                estops = 0
            if port.rx_errors:
                cause = port.bus_off()
                if cause is not None:
                    self._on_bus_off(port, cause, now)
        np.equal(got, self.expected, out=self.complete)
        self._decode(now)

    def _emcy(self, axes: tuple[int, ...], code: int, t: float) -> None:
        """An EMCY of the node whose drives are ``axes``: each one's error code."""
        error_code = self._state.error_code
        for j in axes:
            error_code[j] = code
            if code == cia301.EMCY_STO:
                self._bringups[j].sto_seen = True
        # An EMCY does not say which axis of a multi-axis node it is about: there each
        # axis is faulted by its own statusword, not by the EMCY
        if len(axes) == 1:
            self._sup.on_emcy(axes[0], code, t)

    def _decode(self, now: float) -> None:
        """The raw values into JointState, in SI units, with each drive's CiA 402 state."""
        s, raw, sc = self._state, self._raw, self._scaling
        np.copyto(s.fresh, self.complete)
        sc.decode(raw["position"], sc.position, s.position)
        sc.decode(raw["velocity"], sc.velocity, s.velocity)
        sc.decode(raw["torque"], sc.torque, s.torque)
        np.copyto(s.statusword, raw["statusword"], casting="unsafe")
        cia402.states_from_statuswords(s.statusword, s.cia402_state)
        s.time = now

    def _heartbeat(self, i: int, byte: int, t: float) -> None:
        nmt_state: int | None = byte
        if self._guarding.guarded[i]:  # a guard answer: toggle bit 7, the state below it
            nmt_state = self._guarding.answer(i, byte)
        if nmt_state is None:
            return
        for k in self._node[i]:  # every axis of the node: its NMT state is theirs
            self.hb_state[k] = nmt_state
            self.hb_time[k] = t
            self._bringups[k].alive = True
            self._sup.on_heartbeat(k, nmt_state, t)


def _received_until(port: BusPort, now: float) -> float:
    """Before draining: every frame that arrived before this is in the port's ``rx`` now.
    A reader starved past a deadline (a frozen process) has heartbeats in time still
    unread; the deadline waits for them (a dead reader judges on ``now``)."""
    cb = port.canopen
    reader = cb.reader if cb is not None else None
    if cb is None or reader is None or not reader.alive:
        return now
    return min(now, reader.received_until(cb.bus))
