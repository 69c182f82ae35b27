"""The identity object (CiA 301, 0x1018): which device answers at a node id.

Vendor-ID (0x1018:1, assigned by CiA), product code (:2), revision number (:3) and serial
number (:4) say which drive is on the bus, so a scan can tell one from another, a generated
config can match a drive to its vendor's file, and bring-up can refuse a drive that is not
the one the config was written for (swapped node ids or cables make a robot move the wrong
joint). The simulator gives each simulated drive one of these.

What bring-up requires of a drive (``IdentityCheck``): the fields its config's
``identity:`` names, and for the vendor-ID and product code it does not name, the ones its
EDS/DCF is for (a file for vendor X driving a drive of vendor Y is a wrong file or a wrong
drive). ``identity: any`` requires nothing; a file that names no vendor (a generic one)
constrains nothing, nor does a product number a file does not give.

``file_fit`` is the same rule seen from a folder of files (``init-config``): a file bring-up
would refuse for a device is not for it; one that names the device's vendor and product is
made for it; the rest may fit, and say what they leave open (no vendor, no product number).
"""
from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal, Protocol

import canopen
from canopen import objectdictionary

from ...errors import WrongDevice
from ..protocol.cia301 import IDENTITY

#: the subindices of 0x1018, in field order
SUBINDEX = {"vendor_id": 1, "product_code": 2, "revision": 3, "serial": 4}
#: ``identity: any`` in a drive's config: no identity check at all
ANY: Literal["any"] = "any"
_U32 = 0xFFFF_FFFF


def _u32(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= _U32


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
            if value is not None and not _u32(value):
                raise ValueError(f"identity {f.name} must be an unsigned 32-bit integer, "
                                 f"got {value!r}")

    def known(self) -> dict[str, int]:
        """The known fields by name, in field order."""
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) is not None}

    def objects(self) -> dict[tuple[int, int], int]:
        """The known fields as (0x1018, subindex) -> value."""
        return {(IDENTITY, SUBINDEX[name]): v for name, v in self.known().items()}

    def describe(self) -> str:
        return _fields(self.known()) or "unknown"


def _fields(values: Mapping[str, int]) -> str:
    return ", ".join(f"{name} 0x{v:08X}" for name, v in values.items())


def identity_from_config(value: Any, where: str) -> Identity | Literal["any"] | None:
    """A drive's ``identity:`` as YAML gives it: a mapping of any of vendor_id,
    product_code, revision, serial (integers; YAML reads an unquoted 0x1234 as one), or
    ``any``. ValueError naming ``where`` and the key for anything else."""
    if value is None or isinstance(value, Identity):
        return value
    if value == ANY:
        return ANY
    keys = ", ".join(SUBINDEX)
    if not isinstance(value, Mapping) or not value:
        raise ValueError(f"{where}: identity must be {ANY!r} (not checked) or a mapping of "
                         f"one or more of {keys}, got {value!r}")
    for key, given in value.items():
        if key not in SUBINDEX:
            raise ValueError(f"{where}: identity.{key}: unknown key (known: {keys})")
        if not _u32(given):
            hint = " (write a hex number unquoted: 0x1234)" if isinstance(given, str) else ""
            raise ValueError(f"{where}: identity.{key} must be an unsigned 32-bit integer "
                             f"(0..0xFFFFFFFF){hint}, got {given!r}")
    return Identity(**dict(value))


def file_identity(od: objectdictionary.ObjectDictionary) -> Identity:
    """The vendor-ID and product code an EDS/DCF is for: its [DeviceInfo] VendorNumber and
    ProductNumber, else its 0x1018:1/2 values; 0 is none (a generic file's)."""
    info = od.device_information

    def pick(stated: Any, subindex: int) -> int | None:
        if _u32(stated) and stated:
            return int(stated)
        var = od.get_variable(IDENTITY, subindex)
        value = None if var is None else var.value if var.value is not None else var.default
        return int(value) if _u32(value) and value else None
    return Identity(vendor_id=pick(info.vendor_number, 1),
                    product_code=pick(info.product_number, 2))


@dataclass(frozen=True)
class IdentityCheck:
    """What bring-up requires of a node's 0x1018, each value with where it comes from."""
    configured: Identity = Identity()  # the config's identity:
    from_file: Identity = Identity()   # the file's vendor-ID/product code the config leaves
    file: str = ""                     # the file's name, for the refusal
    opted_out: bool = False            # identity: any

    @classmethod
    def of(cls, configured: Identity | Literal["any"] | None,
           od: objectdictionary.ObjectDictionary, source: str) -> IdentityCheck:
        if configured == ANY:
            return cls(opted_out=True)
        given = configured if isinstance(configured, Identity) else Identity()
        own = file_identity(od)
        said = given.known()
        from_file = Identity(**{k: v for k, v in own.known().items() if k not in said}) \
            if own.vendor_id is not None else Identity()
        return cls(given, from_file, Path(source).name)

    @property
    def wanted(self) -> tuple[str, ...]:
        """The fields bring-up reads, in field order."""
        return tuple(name for name in SUBINDEX
                     if name in self.configured.known() or name in self.from_file.known())

    def describe(self) -> str:
        """check-config's line for the drive."""
        if self.opted_out:
            return "identity: any (not checked)"
        if not self.wanted:
            return "identity: not checked: its file names no vendor"
        parts = []
        if self.configured.known():
            parts.append(f"{_fields(self.configured.known())} required")
        if self.from_file.known():
            parts.append(f"vendor/product from its file ({_fields(self.from_file.known())})")
        return "identity: " + "; ".join(parts)

    def problem(self, found: Identity,
                others: Sequence[tuple[str, IdentityCheck]] = ()) -> str | None:
        """Why the device that answered ``found`` is not this drive, or None. A field the
        device does not have is compared only where the config asks for it. ``others``:
        the config's other drives (how each is named, its check): a device that is one of
        them is a swap of node ids or cables; a swap is not suggested otherwise."""
        have = found.known()
        wrong = {name: f"{name} 0x{v:08X} expected, " + (
                     f"0x{have[name]:08X} found" if name in have
                     else f"the drive has no 0x{IDENTITY:04X}:{SUBINDEX[name]}")
                 for name, v in self.configured.known().items() if have.get(name) != v}
        twin = next((named for named, other in others
                     if other.configured.known() and other.problem(found) is None), None)
        hint = (f"it is {twin}: swapped node ids or cables?" if twin is not None
                else "another drive of the same model (replaced?)" if set(wrong) == {"serial"}
                else "not the drive the config names")
        why = [f"{'; '.join(wrong.values())}: {hint}"] if wrong else []
        mismatch = file_mismatch(self.from_file, found, self.file)
        if mismatch is not None:
            why.append(mismatch)
        return "; ".join(why) or None


def file_mismatch(meant: Identity, found: Identity, file: str) -> str | None:
    """Why a device that answered ``found`` is not one the file ``file`` is for, which
    names ``meant`` (its vendor-ID and product code, as ``IdentityCheck.from_file`` keeps
    them), or None: a field the file names and the device says otherwise. The one rule of
    bring-up's check and of init-config's choice of files."""
    have, said = found.known(), meant.known()
    if not any(name in have and have[name] != v for name, v in said.items()):
        return None
    seen = _fields({name: have[name] for name in said if name in have})
    return f"{seen} found, its file {file} is for {_fields(said)}: wrong file or wrong drive?"


@dataclass(frozen=True)
class FileFit:
    """How a device file fits a device (``file_fit``): ``wrong`` why it is not for it
    (bring-up would refuse them together), else ``open`` what it leaves open, a person's
    to decide; neither: the file is made for the device."""
    wrong: str | None = None
    open: str | None = None

    @property
    def made_for(self) -> bool:
        return self.wrong is None and self.open is None


def file_fit(od: objectdictionary.ObjectDictionary, found: Identity, file: str) -> FileFit:
    """How the file ``file`` (its object dictionary ``od``) fits the device that answered
    ``found``: bring-up's rule (``IdentityCheck`` of a drive whose config names no
    identity), then what the file names. Made for it: the file names the device's vendor
    and product (or, where neither names a vendor, vendor-ID 0, the file's product is the
    device's)."""
    check = IdentityCheck.of(None, od, file)
    wrong = file_mismatch(check.from_file, found, Path(file).name)
    if wrong is not None:
        return FileFit(wrong=wrong)
    own, have = file_identity(od), found.known()
    if own.vendor_id is None:
        if not found.vendor_id and own.product_code is not None \
                and own.product_code == found.product_code:
            return FileFit()
        return FileFit(open="it names no vendor: a generic file, for any vendor's drive")
    if own.product_code is None:
        return FileFit(open=f"it names vendor 0x{own.vendor_id:08X} and no product number: "
                            "any product of that vendor fits it")
    missing = [f"0x{IDENTITY:04X}:{SUBINDEX[k]}" for k in ("vendor_id", "product_code")
               if k not in have]
    if missing:
        return FileFit(open=f"the device does not say its {' or '.join(missing)}")
    return FileFit()


class Uploads(Protocol):
    """An SDO client as bring-up has it (bringup/named_sdo.py): an abort raises
    canopen.SdoAbortedError."""

    def upload(self, index: int, subindex: int) -> bytes: ...


def read_identity(sdo: Uploads, names: Iterable[str]) -> Identity:
    """The named fields of the device's 0x1018; None for a subindex it does not have."""
    values: dict[str, int] = {}
    for name in names:
        try:
            data = sdo.upload(IDENTITY, SUBINDEX[name])
        except canopen.SdoAbortedError:
            continue
        values[name] = struct.unpack("<I", data[:4].ljust(4, b"\0"))[0]
    return Identity(**values)


def verify_identity(sdo: Uploads, check: IdentityCheck,
                    others: Sequence[tuple[str, IdentityCheck]] = ()) -> None:
    """Raise WrongDevice when the device is not the one ``check`` requires (nothing is read
    when it requires nothing); ``others`` as IdentityCheck.problem's."""
    if not check.wanted:
        return
    why = check.problem(read_identity(sdo, check.wanted), others)
    if why is not None:
        raise WrongDevice(why)
