"""The demo's last check: the loop's stop sent every drive its torque-off (an RPDO with
controlword 0x0000), seen from outside the manager, on bus handles of the demo's own.

The handles and their reader open when the walk-through ends (``arm``), just before the
loop's stop: open all along, they took every cycle's controlword RPDOs (12 a cycle for 12
drives at 1 kHz) on a thread of the loop's process whose turns with the GIL were the largest
share of the loop's waits in the demo's slowest cycles (traced). A frame sent once ``arm``
has returned waits in its handle's queue for the reader, so none of the stop's is missed.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import can

if TYPE_CHECKING:
    from ..drivers.bus import BusReader
    from ..runtime.config import RuntimeConfig


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
    which must come): what failed is ``error``."""

    def __init__(self, config: RuntimeConfig,
                 open_bus: Callable[[str, set[int]], can.BusABC]) -> None:
        self.probes = [TorqueOffProbe(controlword_carriers(config, b.label))
                       for b in config.buses]
        self.error: str | None = None
        self._channels = [b.channel for b in config.buses]
        self._open = open_bus
        self._buses: list[can.BusABC] = []
        self._readers: list[BusReader] = []

    def arm(self) -> None:
        from ..drivers.bus import readers_for
        try:
            for channel, probe in zip(self._channels, self.probes):
                self._buses.append(self._open(channel, set(probe.carriers)))
            self._readers = readers_for([(bus, (probe,)) for bus, probe
                                         in zip(self._buses, self.probes)],
                                        name="demo-probes")
        except Exception as exc:  # noqa: BLE001 - the check fails, saying why; the stop comes
            self.error = f"the probes' buses did not open: {type(exc).__name__}: {exc}"

    def seen(self) -> int:
        """Drives whose torque-off the probes saw."""
        return sum(len(probe.seen) for probe in self.probes)

    def close(self) -> None:
        for reader in self._readers:
            reader.stop()
        for bus in self._buses:
            bus.shutdown()
        self._readers, self._buses = [], []

