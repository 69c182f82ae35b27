"""The identity object (CiA 301, 0x1018): which device answers at a node id.

Vendor-ID (0x1018:1, assigned by CiA), product code (:2), revision number (:3) and serial
number (:4) say which drive is on the bus, so a scan can tell one from another, a generated
config can match a drive to its vendor's file, and bring-up can refuse a drive that is not
the one the config was written for (swapped node ids or cables make a robot move the wrong
joint). The simulator gives each simulated drive one of these.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

from .cia301 import IDENTITY

#: the subindices of 0x1018, in field order
SUBINDEX = {"vendor_id": 1, "product_code": 2, "revision": 3, "serial": 4}


@dataclass(frozen=True)
class Identity:
    """0x1018:1..4 of one node; None: not known (not read, or the device has no such
    subindex: only the vendor-ID is mandatory)."""
    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None and (not isinstance(value, int) or isinstance(value, bool)
                                      or not 0 <= value <= 0xFFFF_FFFF):
                raise ValueError(f"identity {f.name} must be an unsigned 32-bit integer, "
                                 f"got {value!r}")

    def objects(self) -> dict[tuple[int, int], int]:
        """The known fields as (0x1018, subindex) -> value."""
        return {(IDENTITY, SUBINDEX[f.name]): v for f in fields(self)
                if (v := getattr(self, f.name)) is not None}

    def describe(self) -> str:
        return ", ".join(f"{f.name} 0x{v:08X}" for f in fields(self)
                         if (v := getattr(self, f.name)) is not None) or "unknown"
