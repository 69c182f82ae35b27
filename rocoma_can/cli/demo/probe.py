"""The demo's last check: the loop's stop sent every drive its torque-off (an RPDO with
controlword 0x0000), seen from outside the manager, on bus handles of the demo's own.

The handles and their reader open when the walk-through ends (``arm``), just before the
operator stops the loop: open all along, they took every cycle's controlword RPDOs (12 a
cycle for 12 drives at 1 kHz) on a thread of the loop's process whose turns with the GIL
were the largest share of the loop's waits in the demo's slowest cycles (traced). A frame
sent once ``arm`` has returned waits in its handle's queue for the reader, so the
operator's stop loses none. A loop that stopped before (a signal, its time limit) sent its
torque-off unseen: ``arm`` then opens nothing and says so in ``error``.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

import can

from ...node.objects import STATE_NAMES

if TYPE_CHECKING:
    from ...drivers.link.bus import BusReader
    from ...runtime.config import RuntimeConfig


class TorqueOffProbe(can.Listener):
    """On one bus (its reader's thread): which drives got an RPDO with controlword 0x0000
    (disable voltage). ``carriers``: COB-ID -> (drive, byte offset of the controlword) of the
    RPDO that carries each drive's controlword (RPDO1 at 0 for the generic drive; a fixed
    mapping may differ)."""

    def __init__(self, carriers: dict[int, tuple[str, int]]) -> None:
        self.carriers = carriers
        self.seen: set[str] = set()

    def on_message_received(self, msg: can.Message) -> None:
        carrier = self.carriers.get(msg.arbitration_id)
        if carrier is not None:
            drive, at = carrier
            if msg.dlc >= at + 2 and msg.data[at] == msg.data[at + 1] == 0:
                self.seen.add(drive)


def controlword_carriers(config: RuntimeConfig, bus: str) -> dict[int, tuple[str, int]]:
    """For the drives on ``bus``: COB-ID -> (drive name, offset) of the first RPDO of each
    drive's layout that carries its controlword."""
    carriers = {}
    first = config.buses[0].label
    for drive in config.drives:
        if (drive.bus or first) != bus:
            continue
        for pdo in config.plans[drive.name].layout.rpdos:
            if "controlword" in pdo.names:
                at = sum(e.size for e in pdo.entries[:pdo.names.index("controlword")])
                carriers[pdo.cob_id] = (drive.name, at)
                break
    return carriers


class TorqueOffProbes:
    """A probe per bus of ``config``; ``open_bus(channel, filters)`` opens a handle that
    passes only ``filters``' COB-IDs. ``arm`` never raises (it runs before the loop's stop,
    which must come): what failed is ``error``. Once closed (the demo's end, which may come
    before a stuck operator arms), ``arm`` opens nothing; a second ``arm`` neither."""

    def __init__(self, config: RuntimeConfig,
                 open_bus: Callable[[str, set[int]], can.BusABC]) -> None:
        self.probes = [TorqueOffProbe(controlword_carriers(config, b.label))
                       for b in config.buses]
        self.error: str | None = None
        self._channels = [b.channel for b in config.buses]
        self._open = open_bus
        self._buses: list[can.BusABC] = []
        self._readers: list[BusReader] = []
        self._lock = threading.Lock()  # arm (the operator's thread) against close
        self._done = False  # armed or closed

    def arm(self, stopped: str | None = None) -> None:
        """Open the handles and their reader; ``stopped``: why the loop already stopped, if
        it did (nothing is opened: its torque-off went out unseen)."""
        with self._lock:
            if self._done:
                return
            self._done = True
            if stopped is not None:
                self.error = f"the loop stopped ({stopped}) before the probes opened"
                return
            try:
                from ...drivers.link.bus import readers_for
                for channel, probe in zip(self._channels, self.probes):
                    self._buses.append(self._open(channel, set(probe.carriers)))
                self._readers = readers_for([(bus, (probe,)) for bus, probe
                                             in zip(self._buses, self.probes)],
                                            name="demo-probes")
            except Exception as exc:  # noqa: BLE001 - the check fails saying why; the stop
                # comes in any case
                self.error = f"the probes' buses did not open: {type(exc).__name__}: {exc}"

    def seen(self) -> int:
        """Drives whose torque-off the probes saw."""
        return sum(len(probe.seen) for probe in self.probes)

    def judge(self, stop_reason: str, last_state: int, drives: int, interrupted: bool
              ) -> tuple[bool, str]:
        """The last step's verdict and detail: every drive's torque-off seen, the manager
        ended in FAILPROOF (0). A demo interrupted before the probes opened cannot have
        seen them: said skipped, with the state the manager ended in."""
        if interrupted and self.error:
            return last_state == 0, (f"skipped: {self.error}: its torque-off frames went out "
                                     f"unwatched; the manager ended in "
                                     f"{STATE_NAMES[last_state]}")
        got, buses = self.seen(), len(self.probes)
        return last_state == 0 and got == drives, (
            f"{stop_reason}; controlword 0x0000 seen from {got}/{drives} drives' RPDOs"
            + (f" on {buses} buses" if buses > 1 else "")
            + (f"; {self.error}" if self.error else ""))

    def close(self) -> None:
        with self._lock:
            self._done = True
            for reader in self._readers:
                reader.stop()
            for bus in self._buses:
                bus.shutdown()
            self._readers, self._buses = [], []

