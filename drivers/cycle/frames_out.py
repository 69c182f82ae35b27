"""Every frame the cycle sends to the drives, torque-off first: a safety review starts here.

Frames are allocated at start-up, torque-off ones encoded then too: sending them takes no
arithmetic and no branch that can raise. ``BusPort.send`` never raises or blocks: a refused
frame is counted; refused cycle after cycle, a bus fault. What goes out (hardware.py):

* FAILPROOF: ``torque_off`` to every drive whose PDOs are configured, whatever JointCommand
  holds: controlword 0x0000 (disable voltage), the drive's default mode, every target 0.
* a hung update(): ``watchdog_torque_off`` (the manager's watchdog thread): the same frames
  and SYNC, no heartbeat: a loop that never returns is still caught by the drives' 0x6007.
* OK / EMERGENCY: ``off`` for a drive not under command (in bring-up, latched, not armed),
  ``rpdos`` for one under command with the values command.py chose.
* then every cycle: ``sync_and_heartbeat`` and node_guarding.py's guard requests, from the
  cycle only: a loop that stops or hangs falls silent and the drives switch themselves off.
"""
from __future__ import annotations

from collections.abc import Sequence

import can

from ..bringup.drive_bringup import DriveBringup
from ..link.bus_port import BusPort
from ..protocol import cia402
from ..protocol.wire import picker
from .drive_table import DriveTable


class FramesOut:
    """Frames of N drives, each to the bus it sits on; SYNC and the manager's heartbeat
    (every ``heartbeat_period`` s) on every bus."""

    def __init__(self, table: DriveTable, *, ports: Sequence[BusPort],
                 heartbeat_period: float) -> None:
        self._layouts = layouts = [d.layout for d in table]
        self._port_of = port_of = [d.port for d in table]
        self._default_mode = [int(d.config.modes[0]) for d in table]
        self._ports, self._send = ports, [p.send for p in port_of]
        n = range(len(layouts))
        self._torque_off = [self._encode(i, 0) for i in n]
        self._fault_reset = [self._encode(i, int(cia402.Controlword.FAULT_RESET)) for i in n]
        self._probe = [self._encode(i, int(cia402.Controlword.SHUTDOWN)) for i in n]
        # per RPDO: (frame, codec.pack_into, its entries picked from (cw, mode, targets...))
        self._rpdo = [[(port_of[i].frame(p.cob_id, p.size), p.codec.pack_into,
                        picker(p.positions_in(lay.rpdo_fields))) for p in lay.rpdos]
                      for i, lay in enumerate(layouts)]
        self._constants = [lay.rpdo_constants for lay in layouts]
        self._period, self.next_heartbeat = heartbeat_period, float("-inf")  # due next cycle

    def _encode(self, i: int, controlword: int) -> list[can.Message]:
        lay = self._layouts[i]
        values = (controlword, self._default_mode[i], 0, 0, 0, *lay.rpdo_constants)
        frames = [self._port_of[i].frame(pdo.cob_id, pdo.size) for pdo in lay.rpdos]
        for msg, pdo in zip(frames, lay.rpdos):
            pdo.codec.pack_into(msg.data, 0, *picker(pdo.positions_in(lay.rpdo_fields))(values))
        return frames

    def torque_off(self, bringup: Sequence[DriveBringup]) -> None:
        """FAILPROOF: every configured drive off (or in its bring-up's power-off steps)."""
        for i, b in enumerate(bringup):
            if b.mapped:
                self.off(i, b)

    def watchdog_torque_off(self, bringup: Sequence[DriveBringup]) -> None:
        """From any thread: disable voltage to every configured drive, then SYNC."""
        for i, b in enumerate(bringup):
            for msg in self._torque_off[i] if b.mapped else ():
                self._port_of[i].send_elsewhere(msg)
        for port in self._ports:
            port.send_elsewhere(port.sync)

    def off(self, i: int, b: DriveBringup) -> None:
        """Not under command: torque off, or bring-up's fault reset / probe (0x80, 0x06: off)."""
        frames = (self._fault_reset[i] if b.fault_reset_bit
                  else self._probe[i] if b.probing else self._torque_off[i])
        for msg in frames:
            self._send[i](msg)

    def rpdos(self, i: int, values: tuple[int, ...]) -> None:
        """Drive i's RPDOs from (controlword, mode, position, velocity, torque, constants)."""
        values += self._constants[i]
        send = self._send[i]
        for msg, pack_into, pick in self._rpdo[i]:
            pack_into(msg.data, 0, *pick(values))
            send(msg)

    def sync_and_heartbeat(self, now: float) -> None:
        """SYNC on every bus, then the heartbeat when due on 0x1017's grid (a period after
        the last due time, in the first cycle at or after it: never late on average); a grid
        a period behind (a stalled loop, a beat out of turn) restarts from now, no burst."""
        for port in self._ports:
            port.send(port.sync)
        if now >= self.next_heartbeat:
            for port in self._ports:
                port.send(port.heartbeat)
            due = self.next_heartbeat + self._period
            self.next_heartbeat = due if due > now else now + self._period

