"""The drive's SDO client as bring-up uses it: each failure names its object and value.

A configuration is a few dozen SDO exchanges; when the drive refuses one, the failure line
must say which object it refused (not only the abort code), and for axis n of a multi-axis
node every profile object is that axis's own (cia402.on_axis).
"""
from __future__ import annotations

import canopen
from canopen.sdo.client import SdoClient

from ..protocol import cia402


class ObjectRefused(canopen.SdoAbortedError):
    """An SDO abort, naming the object and the value (bring-up's failure line says which
    object the drive refused, not only the abort code)."""

    def __init__(self, code: int, what: str) -> None:
        super().__init__(code)
        self.what = what
        self.aborted = canopen.SdoAbortedError(code)

    def __str__(self) -> str:
        return f"{self.what} refused: {self.aborted}"


class NamedSdo:
    """The drive's SdoClient, each failure naming its object: what configuration uses. For
    axis n of a multi-axis node, a profile object (0x6000-0x67FF) is the axis's own, at
    + (n - 1) x 0x800 (the plan reads the axis at axis 1's indices: capabilities.py)."""

    def __init__(self, sdo: SdoClient, axis: int = 1) -> None:
        self._sdo = sdo
        self.axis = axis

    def upload(self, index: int, subindex: int) -> bytes:
        index = cia402.on_axis(index, self.axis)
        try:
            data: bytes = self._sdo.upload(index, subindex)
            return data
        except canopen.SdoAbortedError as exc:
            raise ObjectRefused(exc.code, f"SDO read of 0x{index:04X}:{subindex}") from exc
        except canopen.SdoCommunicationError as exc:
            raise type(exc)(f"SDO read of 0x{index:04X}:{subindex}: {exc}") from exc

    def download(self, index: int, subindex: int, data: bytes) -> None:
        index = cia402.on_axis(index, self.axis)
        what = f"SDO write of 0x{index:04X}:{subindex} = 0x{int.from_bytes(data, 'little'):X}"
        try:
            self._sdo.download(index, subindex, data)
        except canopen.SdoAbortedError as exc:
            raise ObjectRefused(exc.code, what) from exc
        except canopen.SdoCommunicationError as exc:
            raise type(exc)(f"{what}: {exc}") from exc
