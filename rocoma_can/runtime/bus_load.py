"""Bus load: how many bits one cycle puts on a CAN bus, and what fits.

Per cycle on one bus: every drive's RPDOs and TPDOs, with the layouts the driver will use
(drivers/plan/pdo_layout.py), plus one SYNC, each frame counted with worst-case bit stuffing. A
classic 1 Mbit/s bus carries ~7,400 8-byte frames/s that way; CAN FD with bit rate
switching carries more because its data phase runs at the data bit rate.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from ..drivers.plan.config import DriveConfig
from ..drivers.plan.pdo_layout import DriveLayout, layout_for
from ..drivers.protocol.wire import frame_bits


@dataclass(frozen=True)
class BusLoad:
    drives: int
    rate: float
    bitrate: int
    frames_per_cycle: int
    bits_per_cycle: float        # worst-case stuffing, at the nominal bit rate
    bits_per_drive: float        # mean over the drives, worst case
    data_bitrate: int | None = None  # CAN FD data phase (None: classic CAN)

    @property
    def frames_per_second(self) -> float:
        return self.frames_per_cycle * self.rate

    @property
    def load(self) -> float:
        """Fraction of the bitrate used, worst-case stuffing (heartbeats are < 0.1 %)."""
        return self.bits_per_cycle * self.rate / self.bitrate

    @property
    def max_rate(self) -> float:
        return self.bitrate / self.bits_per_cycle

    @property
    def drives_that_fit(self) -> int:
        sync = frame_bits(0, data_ratio=self.data_ratio)
        return max(0, int((self.bitrate / self.rate - sync) // self.bits_per_drive))

    def explain(self) -> str:
        full_frames = self.bitrate / frame_bits(8, data_ratio=self.data_ratio)
        kind = (f"CAN FD bus ({self.bitrate / 1e6:g}/{self.data_bitrate / 1e6:g} Mbit/s)"
                if self.data_bitrate else f"{self.bitrate / 1e6:g} Mbit/s bus")
        return (f"{self.drives} drives at {self.rate:g} Hz need "
                f"{self.frames_per_second:,.0f} frames/s ({self.load:.0%} of the bus, worst "
                f"case); a {kind} carries ~{full_frames:,.0f} 8-byte frames/s worst case; "
                f"{math.floor(self.max_rate):,} Hz fits {self.drives} drives, "
                f"{self.rate:g} Hz fits {self.drives_that_fit}")

    @property
    def data_ratio(self) -> float | None:
        return None if self.data_bitrate is None else self.bitrate / self.data_bitrate


def bus_load(drives: Sequence[DriveConfig | DriveLayout], rate: float, bitrate: int,
             data_bitrate: int | None = None) -> BusLoad:
    """Per cycle on one bus: every drive's RPDOs and TPDOs (the driver's layouts: give
    them, or drive configs of generic drives) and one SYNC; ``data_bitrate``: a CAN FD bus
    with bit rate switching at that data rate."""
    ratio = None if data_bitrate is None else bitrate / data_bitrate
    frames, bits = 1, frame_bits(0, data_ratio=ratio)
    drive_bits = 0.0
    for d in drives:
        layout = d if isinstance(d, DriveLayout) else layout_for(d)
        for pdo in layout.rpdos + layout.tpdos:
            frames += 1
            drive_bits += frame_bits(pdo.size, data_ratio=ratio)
    bits += drive_bits
    return BusLoad(len(drives), rate, bitrate, frames, bits,
                   drive_bits / max(1, len(drives)), data_bitrate)
