"""Reading a vendor's EDS or DCF the way the vendors' own tools do: tolerant, and saying so.

Device description files in the field are written by hand, by old tools and by scanners.
canopen's importer reads strict INI text; it fails on a comment in an old DOS code page or
a key given twice, and it reads what it can of the rest in ways that hide a problem: a
two's-complement hex default of a signed object (``0xFFFF`` for INTEGER16) becomes a value
it cannot encode, an empty ``DefaultValue=`` and a missing one both become None, a DCF
exported for node 1 carries ``0x201`` where its EDS said ``$NODEID+0x200``. This module
reads the text once, repairs what has one reading, and hands canopen a normalised copy:

- bytes that are not UTF-8 are read as Latin-1 (noted once);
- any line ending; a key given twice in a section: the last one wins (noted); a section
  given twice: merged;
- ``DeviceCommissioning`` (as some tools spell it) is CiA 306's ``DeviceComissioning``;
  ``$NodeID`` in any case is ``$NODEID``; keys and ``1600SUB1``-style names in any case;
- numbers in decimal (leading zeros too), hex in either case, and two's-complement hex for
  signed types, rewritten as the decimal value they mean;
- objects of a custom ``[TypeDefinitions]`` record type (manufacturer data) as domains;
- names where a number belongs, as some tools write them (``ObjectType=VAR``,
  ``DataType=UNSIGNED16``, ``PDOMapping=TRUE``), as that number; an object without a
  ``ParameterName`` named by its index; a manufacturer object (0x2000-0x5FFF) that cannot
  be read (no ``DataType``, a data type that is no number) left out, noted: rocoma-can
  commands none; the same in a standard object refuses the file naming its section and key;
- header values canopen reads as numbers ([DeviceInfo], [DeviceComissioning],
  [DummyUsage], [Comments]) that are none: left out, noted;
- a node-relative COB-ID (``DefaultValue=$NODEID+0x200``) whose ``ParameterValue`` was
  baked in for another node (``0x201``) is re-derived for the node id in use (noted).

What the file lists without any value stays unknown (``DeviceFile.unknown``): the drive is
asked for it at start-up instead of taking it as 0.
"""
from __future__ import annotations

import io
import re
from dataclasses import dataclass, field

from canopen import objectdictionary
from canopen.objectdictionary import datatypes

from ...user_files import read_regular
from ..protocol.cia301 import ObjectKey

_INDEX_SECTION = re.compile(r"([0-9A-Fa-f]{4})(?:sub([0-9A-Fa-f]{1,2}))?", re.IGNORECASE)
_NODE_ID = re.compile(r"\$node_?id", re.IGNORECASE)
_INLINE_COMMENT = re.compile(r"\s;.*$")
#: Keys canopen reads case-sensitively, by their lower-case spelling.
_KEYS = {k.lower(): k for k in (
    "ParameterName", "ObjectType", "DataType", "AccessType", "DefaultValue",
    "ParameterValue", "PDOMapping", "LowLimit", "HighLimit", "SubNumber", "CompactSubObj",
    "ObjFlags", "StorageLocation", "NrOfEntries", "Denotation", "VendorName",
    "VendorNumber", "ProductName", "ProductNumber", "RevisionNumber", "OrderCode",
    "NodeID", "NodeName", "Baudrate", "NetNumber", "SupportedObjects", "Lines")}
_SECTIONS = {"devicecommissioning": "DeviceComissioning",
             "devicecomissioning": "DeviceComissioning",
             "deviceinfo": "DeviceInfo", "fileinfo": "FileInfo", "comments": "Comments",
             "typedefinitions": "TypeDefinitions", "dummyusage": "DummyUsage",
             "mandatoryobjects": "MandatoryObjects", "optionalobjects": "OptionalObjects",
             "manufacturerobjects": "ManufacturerObjects"}
_SIGNED_BITS = {datatypes.INTEGER8: 8, datatypes.INTEGER16: 16, datatypes.INTEGER32: 32,
                datatypes.INTEGER64: 64}
_NOT_NUMBERS = (datatypes.VISIBLE_STRING, datatypes.UNICODE_STRING, datatypes.OCTET_STRING,
                datatypes.DOMAIN, *datatypes.FLOAT_TYPES)
_VALUE_KEYS = ("DefaultValue", "ParameterValue", "LowLimit", "HighLimit")
#: Communication objects whose value is a COB-ID (sub-index 1 of the SDO/PDO parameters)
_COB_ID_SUB1 = ((0x1200, 0x12FF), (0x1400, 0x15FF), (0x1800, 0x19FF))
_COB_ID_SUB0 = (0x1012, 0x1014)


#: the largest EDS/DCF read: vendors' files are up to ~0.2 MiB; this bounds what a wrong
#: file (a log, an image) costs to read and parse
MAX_DEVICE_FILE_BYTES = 8 << 20


class DeviceFileError(ValueError):
    """The file cannot be read as an EDS/DCF at all (not found, not INI text)."""


@dataclass
class DeviceFile:
    """One EDS/DCF as read: canopen's input, and what the reading had to assume."""
    path: str
    sections: dict[str, dict[str, str]]
    notes: list[str] = field(default_factory=list)
    #: objects the file lists with neither DefaultValue nor ParameterValue (or empty ones)
    unknown: set[ObjectKey] = field(default_factory=set)
    commissioned_node_id: int | None = None
    #: the node its COB-IDs are re-derived for (``for_node``); None: as the file gives them
    node_id: int | None = None

    def text(self) -> str:
        out = io.StringIO()
        for name, keys in self.sections.items():
            out.write(f"[{name}]\n")
            for key, value in keys.items():
                out.write(f"{key}={value}\n")
            out.write("\n")
        return out.getvalue()

    def object_dictionary(self, node_id: int) -> objectdictionary.ObjectDictionary:
        """canopen's object dictionary of this file for ``node_id`` ($NODEID resolved, COB-IDs
        baked in for another node re-derived: see ``for_node``)."""
        stream = io.StringIO(self.for_node(node_id).text())
        stream.name = "normalised.dcf"  # canopen picks its importer by the name's suffix
        od = objectdictionary.import_od(stream, node_id)
        od.node_id = node_id
        _check_mappings(self.path, od)
        return od

    def for_node(self, node_id: int) -> DeviceFile:
        """A copy whose node-relative COB-IDs, given as absolute values for some other node
        in ``ParameterValue``, are relative again (a DCF exported for node 1, an EDS carrying
        a commissioning tool's values): the file's COB-ID meant "this node's PDO"."""
        if self.node_id == node_id:
            return self
        sections = {name: dict(keys) for name, keys in self.sections.items()}
        copy = DeviceFile(self.path, sections, list(self.notes), set(self.unknown),
                          self.commissioned_node_id, node_id)
        rebased: list[str] = []
        baked_for: set[int] = set()
        for name, keys in sections.items():
            key = _object_key(name)
            if key is None or not _is_cob_id(key):
                continue
            default, value = keys.get("DefaultValue", ""), keys.get("ParameterValue", "")
            base = _relative_base(default)
            number = _int(value)
            if base is None or number is None or _NODE_ID.search(value):
                continue
            baked = (number & 0x7FF) - (base & 0x7FF)  # flag bits (31, 30) may differ
            if 1 <= baked <= 127 and baked != node_id:
                keys["ParameterValue"] = \
                    f"$NODEID+0x{(number & ~0x7FF) | (base & 0x7FF):X}"
                rebased.append(f"0x{key[0]:04X}:{key[1]} 0x{number:X}")
                baked_for.add(baked)
        if rebased:
            nodes = ", ".join(str(n) for n in sorted(baked_for))
            copy.notes.append(
                f"COB-IDs the file gives for node {nodes} re-derived for node {node_id}: "
                f"{', '.join(rebased[:4])}"
                + (f" and {len(rebased) - 4} more" if len(rebased) > 4 else ""))
        return copy


def _check_mappings(path: str, od: objectdictionary.ObjectDictionary) -> None:
    """A PDO mapping whose sub-index 0 counts more entries than the file gives cannot be
    what the drive does: refused here, so check-config, the master and the simulator
    refuse the file with the same line."""
    for index in (*range(0x1600, 0x1800), *range(0x1A00, 0x1C00)):
        mapping = od.get(index)
        if not isinstance(mapping, objectdictionary.ODRecord | objectdictionary.ODArray) \
                or 0 not in mapping:
            continue
        count_var = mapping[0]
        count = count_var.value if count_var.value is not None else count_var.default
        entries = len([s for s in mapping.subindices if s > 0])
        if isinstance(count, int) and count > entries:
            raise DeviceFileError(f"{path}: 0x{index:04X}:0 says {count} mapped objects but "
                                  f"the file gives {entries} (0x{index:04X}:1..{entries})")


def read_device_file(path: str) -> DeviceFile:
    """Read and normalise an EDS/DCF; DeviceFileError (one line, naming the file) when it is
    not one."""
    try:  # (a FIFO or a device would hang the command: user_files.py)
        raw = read_regular(path, MAX_DEVICE_FILE_BYTES + 1)
    except OSError as exc:
        raise DeviceFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(raw) > MAX_DEVICE_FILE_BYTES:
        raise DeviceFileError(f"{path}: larger than {MAX_DEVICE_FILE_BYTES >> 20} MiB; not an "
                              "EDS/DCF (the largest vendor files are ~0.2 MiB)")
    notes: list[str] = []
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):  # UTF-16 with its byte-order mark
        raw = raw.decode("utf-16", errors="replace").encode("utf-8")
        notes.append("UTF-16 text: read as such")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        text = raw.decode("latin-1")
        notes.append(f"not UTF-8 (byte 0x{raw[exc.start]:02X} on line {line}): read as "
                     "Latin-1")
    sections = _parse(path, text, notes)
    if not any(_object_key(name) is not None for name in sections):
        raise DeviceFileError(f"{path}: not an EDS/DCF file (no object sections such as "
                              "[1000])")
    _expand_compact(sections)
    device = DeviceFile(path, sections, notes)
    _check_headers(device)
    _check_objects(device)
    _normalise_objects(device)
    commissioning = sections.get("DeviceComissioning", {})
    node = _int(commissioning.get("NodeID", ""))
    device.commissioned_node_id = node if node is not None and 1 <= node <= 127 else None
    return device


def _parse(path: str, text: str, notes: list[str]) -> dict[str, dict[str, str]]:
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    name = ""
    duplicates: list[str] = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line[0] in ";#":
            continue
        if line.startswith("["):
            if not line.endswith("]"):
                raise DeviceFileError(f"{path}: line {number}: {line[:40]!r} is not a "
                                      "[section] header")
            name = _section_name(line[1:-1].strip())
            current = sections.setdefault(name, {})
            continue
        if current is None:
            raise DeviceFileError(f"{path}: not an EDS/DCF file (line {number}, "
                                  f"{line[:40]!r}, comes before any [section])")
        key, sep, value = line.partition("=")
        if not sep:
            continue  # a stray word: the vendors' tools skip it too
        key = key.strip()
        key = _KEYS.get(key.lower(), key)
        value = _INLINE_COMMENT.sub("", value).strip()
        if key in current:
            duplicates.append(f"{key!r} in [{name}] (line {number})")
        current[key] = value
    if duplicates:
        notes.append(f"{len(duplicates)} duplicate key(s), the last one used: "
                     + ", ".join(duplicates[:3]) + (" ..." if len(duplicates) > 3 else ""))
    return sections


def _expand_compact(sections: dict[str, dict[str, str]]) -> None:
    """An array given as ``CompactSubObj=N`` (CiA 306: sub-objects 1..N alike, their names in
    ``[xxxxName]``, a DCF's values in ``[xxxxValue]``) written out as its sub-objects:
    canopen keeps only sub-index 1 of such an array, so a compact PDO mapping of eight
    entries would read as one. Sub-index 0 is the highest sub-index, except where CiA 301
    gives it another meaning: a PDO mapping's count of mapped objects (its leading non-zero
    entries, writable as its entries are) and 0x1003's count of errors (0)."""
    for name in list(sections):
        keys = sections.get(name, {})  # (a [xxxxName] or [xxxxValue] is gone once read)
        count = _int(keys.get("CompactSubObj", ""))
        if not _INDEX_SECTION.fullmatch(name) or "sub" in name or count is None \
                or not 1 <= count <= 254:
            continue
        index = int(name, 16)
        names = sections.pop(f"{name}Name", {})
        values = sections.pop(f"{name}Value", {})
        sections.pop(f"{name}Denotation", None)
        title = keys.get("ParameterName", f"0x{name}")
        subs: dict[str, dict[str, str]] = {}
        for n in range(1, count + 1):
            sub = {"ParameterName": names.get(str(n), f"{title} {n}"), "ObjectType": "0x7"}
            sub |= {k: v for k, v in keys.items() if k in (
                "DataType", "AccessType", "PDOMapping", "DefaultValue", "LowLimit", "HighLimit")}
            if values.get(str(n), "").strip():
                sub["ParameterValue"] = values[str(n)]
            subs[f"{name}sub{n:X}"] = sub
        mapping = 0x1600 <= index < 0x1800 or 0x1A00 <= index < 0x1C00
        if mapping:
            given = [_int(sub.get("ParameterValue", sub.get("DefaultValue", "")))
                     for sub in subs.values()]
            first = next((n for n, entry in enumerate(given) if not entry), len(given))
        sub0 = {"ParameterName": "Highest sub-index supported", "ObjectType": "0x7",
                "DataType": "0x0005", "PDOMapping": "0",
                "AccessType": keys.get("AccessType", "ro") if mapping or index == 0x1003
                else "ro",
                "DefaultValue": str(first if mapping else 0 if index == 0x1003 else count)}
        sections[name] = {k: v for k, v in keys.items() if k in (
            "ParameterName", "ObjectType", "StorageLocation", "ObjFlags")}
        sections[name]["SubNumber"] = str(count + 1)
        sections.setdefault(f"{name}sub0", sub0)
        for sub_name, sub in subs.items():
            sections.setdefault(sub_name, sub)


def _section_name(name: str) -> str:
    match = _INDEX_SECTION.fullmatch(name)
    if match:
        index = int(match.group(1), 16)
        if match.group(2) is None:
            return f"{index:04X}"
        return f"{index:04X}sub{int(match.group(2), 16):X}"
    return _SECTIONS.get(name.lower(), name)


def _object_key(name: str) -> ObjectKey | None:
    match = _INDEX_SECTION.fullmatch(name)
    if match is None:
        return None
    return int(match.group(1), 16), int(match.group(2) or "0", 16)


def _int(text: str) -> int | None:
    """A number as files write them: decimal (leading zeros too), 0x hex in either case, a
    sign; None for anything else (an expression, empty)."""
    text = text.strip().replace("_", "")
    try:
        if re.fullmatch(r"[+-]?0[xX][0-9A-Fa-f]+", text):
            return int(text, 16)
        if re.fullmatch(r"[+-]?[0-9]+", text):
            return int(text, 10)
    except ValueError:
        return None
    return None


def _relative_base(text: str) -> int | None:
    """``$NODEID+0x200`` -> 0x200; None when the value is not node-relative."""
    compact = text.replace(" ", "")
    if not _NODE_ID.search(compact):
        return None
    rest = _NODE_ID.sub("", compact).strip("+")
    return _int(rest) if rest else 0


def _is_cob_id(key: ObjectKey) -> bool:
    index, sub = key
    if sub == 0:
        return index in _COB_ID_SUB0
    return sub == 1 and any(lo <= index <= hi for lo, hi in _COB_ID_SUB1)


#: what files write where canopen reads a number
_OBJECT_TYPES = {"NULL": 0x0, "DOMAIN": 0x2, "DEFTYPE": 0x5, "DEFSTRUCT": 0x6, "VAR": 0x7,
                 "ARRAY": 0x8, "RECORD": 0x9}
_DATA_TYPES = {name: code for name, code in vars(datatypes).items()
               if name.isupper() and isinstance(code, int) and code <= 0x1B}
_BOOLEANS = {"TRUE": 1, "YES": 1, "FALSE": 0, "NO": 0}
#: header keys canopen reads with int(): section -> keys (BaudRate_* too, in DeviceInfo)
_HEADER_NUMBERS = {
    "DeviceInfo": ("VendorNumber", "ProductNumber", "RevisionNumber", "SimpleBootUpMaster",
                   "SimpleBootUpSlave", "Granularity", "DynamicChannelsSupported",
                   "GroupMessaging", "NrOfRXPDO", "NrOfTXPDO", "LSS_Supported"),
    "DeviceComissioning": ("NodeID", "Baudrate"),
    "DummyUsage": tuple(f"Dummy{n:04d}" for n in range(1, 8))}


def _number(value: str, names: dict[str, int]) -> int | None:
    """A number as files write it, or one of ``names`` (any case); None for neither."""
    number = _int(value)
    return number if number is not None else names.get(value.strip().upper())


def _check_headers(device: DeviceFile) -> None:
    """canopen reads these header values with int() and fails the whole file on one that is
    not a number; rocoma-can needs none of them to run a drive (init-config matches a file
    by VendorNumber/ProductNumber: a file without them matches none)."""
    sections, dropped = device.sections, []
    sections.pop("Comments", None)  # free text; canopen counts its lines with int()
    for section, names in _HEADER_NUMBERS.items():
        keys = sections.get(section)
        if keys is None:
            continue
        for key in (*names, *(k for k in keys if k.startswith("BaudRate_"))):
            if key in keys and _number(keys[key], _BOOLEANS) is None:
                dropped.append(f"[{section}] {key}={keys.pop(key)}")
            elif key in keys:
                keys[key] = str(_number(keys[key], _BOOLEANS))
        if section == "DummyUsage":  # canopen reads all seven
            for key in names:
                keys.setdefault(key, "0")
    if dropped:
        device.notes.append("header values that are not numbers left out: "
                            + ", ".join(dropped[:4])
                            + (f" and {len(dropped) - 4} more" if len(dropped) > 4 else ""))


def _check_objects(device: DeviceFile) -> None:
    """What canopen's importer needs of every object section, checked before it reads them
    (it fails on the first, naming neither section nor key): names for numbers rewritten,
    a missing ParameterName given; a manufacturer object that cannot be read is left out,
    a standard one refuses the file in one line naming the section and the key."""
    sections = device.sections
    broken: dict[int, str] = {}
    for name, keys in sections.items():
        key = _object_key(name)
        if key is None:
            continue
        problem = _repair_object(name, key, keys, sections)
        if problem is not None:
            broken.setdefault(key[0], problem)
    left_out = []
    for index, problem in sorted(broken.items()):
        if not 0x2000 <= index < 0x6000:
            raise DeviceFileError(f"{device.path}: {problem}")
        for name in [n for n in sections if (_object_key(n) or (-1, 0))[0] == index]:
            del sections[name]
        left_out.append(f"0x{index:04X} ({problem})")
    if left_out:
        device.notes.append("manufacturer objects that cannot be read left out (rocoma-can "
                            "commands none): " + "; ".join(left_out[:3])
                            + (f" and {len(left_out) - 3} more" if len(left_out) > 3 else ""))


def _repair_object(name: str, key: ObjectKey, keys: dict[str, str],
                   sections: dict[str, dict[str, str]]) -> str | None:
    """``keys`` as canopen reads them (names for numbers rewritten, a ParameterName given);
    what makes the object unreadable, or None."""
    index, sub = key
    keys.setdefault("ParameterName", f"0x{index:04X}" + (f" sub {sub}" if sub else ""))
    if "sub" in name:
        parent = sections.get(f"{index:04X}")
        if parent is None:
            return f"[{name}] is a sub-index of [{index:04X}], which the file does not have"
        parent_type = _number(parent.get("ObjectType", "7"), _OBJECT_TYPES)
        if parent_type in (0x7, 0x2):
            return None  # canopen reads a sub-index of a variable as nothing: as the drive
    elif "ObjectType" in keys:
        object_type = _number(keys["ObjectType"], _OBJECT_TYPES)
        if object_type is None:
            return f"[{name}] ObjectType={keys['ObjectType']} is not an object type " \
                   "(0x7 VAR, 0x8 ARRAY, 0x9 RECORD)"
        keys["ObjectType"] = f"0x{object_type:X}"
        if object_type not in (0x7, 0x2):
            return None  # an array or record: its sub-indices carry the values
    for needed in ("DataType", "AccessType"):
        if not keys.get(needed):
            return f"[{name}] has no {needed}"
    data_type = _number(keys["DataType"], _DATA_TYPES)
    if data_type is None:
        return f"[{name}] DataType={keys['DataType']} is not a data type"
    keys["DataType"] = f"0x{data_type:04X}"
    if "PDOMapping" in keys:
        mappable = _number(keys["PDOMapping"], _BOOLEANS)
        if mappable not in (0, 1):
            return f"[{name}] PDOMapping={keys['PDOMapping']} is neither 0 nor 1"
        keys["PDOMapping"] = str(mappable)
    return None


def _normalise_objects(device: DeviceFile) -> None:
    sections = device.sections
    custom: set[int] = set()
    for name, keys in sections.items():
        key = _object_key(name)
        if key is None:
            continue
        if "AccessType" in keys:
            keys["AccessType"] = keys["AccessType"].lower()
        data_type = _int(keys.get("DataType", ""))
        if data_type is not None and data_type > 0x1B \
                and f"{data_type:X}sub1" not in sections:
            # a record type of [TypeDefinitions] used as one variable: manufacturer data
            # canopen cannot type; read as a domain (nothing rocoma-can maps or commands)
            custom.add(data_type)
            keys["DataType"] = f"0x{datatypes.DOMAIN:04X}"
            keys.pop("DefaultValue", None)
            keys.pop("ParameterValue", None)
            data_type = datatypes.DOMAIN
        for value_key in _VALUE_KEYS:
            if value_key in keys:
                value = _normalise_value(keys[value_key], data_type)
                if value:
                    keys[value_key] = value
                else:
                    del keys[value_key]
        is_variable = _int(keys.get("ObjectType", "7")) in (None, 7, 2) \
            and "CompactSubObj" not in keys
        if is_variable and "DefaultValue" not in keys and "ParameterValue" not in keys:
            device.unknown.add(key)
    if custom:
        device.notes.append(
            "manufacturer objects of custom record types ("
            + ", ".join(f"0x{t:X}" for t in sorted(custom))
            + ", [TypeDefinitions]) read as domains: rocoma-can does not use them")


def _normalise_value(value: str, data_type: int | None) -> str:
    """One DefaultValue/ParameterValue/limit in a form canopen reads as the file meant it;
    '' when there is none."""
    value = value.strip()
    if not value:
        return ""
    if data_type is None or data_type in _NOT_NUMBERS:
        return value
    if _NODE_ID.search(value):
        return _NODE_ID.sub("$NODEID", value.replace(" ", ""))
    number = _int(value)
    if number is None:
        return value  # an expression canopen may still read; if not, it stays unknown
    bits = _SIGNED_BITS.get(data_type)
    if bits is not None and (1 << (bits - 1)) <= number < (1 << bits):
        number -= 1 << bits  # two's-complement hex for a signed type
    return str(number)
