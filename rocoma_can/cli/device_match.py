"""Which device file (EDS/DCF) is a node's: the files of a folder read once each
(``index_device_files``), then matched to a node a scan found by the rule bring-up checks a
drive's identity with (drivers.files.identity.file_fit): the files made for it, best first,
and those that may fit it with what they leave open (``match``). For ``init-config``."""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # canopen loads when init-config runs: `rocoma-can --help` stays fast
    from canopen.objectdictionary import ObjectDictionary

    from ..drivers.files.identity import Identity

SUFFIXES = (".eds", ".dcf")


@dataclass(frozen=True)
class DeviceFileInfo:
    """One file of the directory (or of ``--eds``): its object dictionary, which the
    identity rule reads, and what ranks it among files made for one device."""
    path: str
    od: ObjectDictionary
    revision: int | None
    node_id: int | None        # a DCF's commissioned node id
    device_type: int | None    # its 0x1000 (None: not given)


def read_file_info(path: str) -> DeviceFileInfo:
    """One device file; DeviceFileError when it is none (drivers.files.device_file)."""
    from ..drivers.files.device_file import read_device_file
    from ..drivers.protocol.cia301 import DEVICE_TYPE
    device = read_device_file(path)
    od = device.object_dictionary(1)
    var = od.get_variable(DEVICE_TYPE, 0)
    device_type = None if var is None else var.value if var.value is not None else var.default
    return DeviceFileInfo(path, od, _number(od.device_information.revision_number),
                          device.commissioned_node_id,
                          device_type if isinstance(device_type, int) else None)


def index_device_files(directory: str) -> tuple[list[DeviceFileInfo], list[str]]:
    """Every EDS/DCF in ``directory`` (not below it) and a note per file it cannot read, or
    that a config cannot name (a name that is not UTF-8: YAML is UTF-8 text)."""
    from ..drivers.files.device_file import DeviceFileError
    files, notes = [], []
    for entry in sorted(os.scandir(directory), key=lambda e: e.name):
        if not entry.name.lower().endswith(SUFFIXES):
            continue
        shown = shown_name(entry.name)
        try:
            if not entry.is_file():
                continue
        except OSError as exc:  # a symbolic link in a loop, say
            notes.append(f"{shown}: not read ({exc.strerror or exc})")
            continue
        if shown != entry.name:
            notes.append(f"{shown}: its name is not UTF-8: a config (UTF-8 text) cannot name "
                         "it; rename it")
            continue
        try:
            files.append(read_file_info(entry.path))
        except DeviceFileError as exc:
            notes.append(f"{shown}: not read ({exc})")
    return files, notes


def shown_name(name: str) -> str:
    """A file name as printable UTF-8 text: the bytes that are not UTF-8 escaped (\\xff)."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return os.fsencode(name).decode("utf-8", "backslashreplace")
    return name


def _number(value: Any) -> int | None:
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if not isinstance(value, str) or not value.strip():
        return None
    try:
        return int(value.strip(), 0)
    except ValueError:
        return None


def match(node_id: int, identity: Identity, device_type: int | None,
          files: Sequence[DeviceFileInfo]
          ) -> tuple[list[DeviceFileInfo], list[tuple[DeviceFileInfo, str]]]:
    """The files made for this device, best first (same revision, then commissioned for
    this node), and those that may fit it, each with what it leaves open (the identity
    rule: drivers.files.identity.file_fit). A file of another device profile than the device's
    (0x1000: the manager's own EDS beside the drives') is for neither."""
    from ..drivers.files.identity import file_fit
    made, may = [], []
    for f in _rank(node_id, identity, files):
        if device_type is not None and f.device_type \
                and f.device_type & 0xFFFF != device_type & 0xFFFF:
            continue
        fit = file_fit(f.od, identity, f.path)
        if fit.made_for:
            made.append(f)
        elif fit.open is not None:
            may.append((f, fit.open))
    return made, may


def _rank(node_id: int, identity: Identity, files: Sequence[DeviceFileInfo]
          ) -> list[DeviceFileInfo]:
    return sorted(files, key=lambda f: (f.revision != identity.revision,
                                        f.node_id not in (None, node_id), f.node_id is None,
                                        f.path))
