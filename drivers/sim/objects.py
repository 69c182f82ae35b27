"""The simulated drive's object dictionary and its SDO server.

Values live in one flat dict keyed by (index, subindex), initialised from the EDS; the other
services of the drive read and write it directly, so the SDO server, the PDOs and the state
machine always see the same object. canopen's SdoServer speaks the protocol (expedited and
segmented; block upload from drivers/protocol/sdo_block_server.py, block download is refused with
0x05040001 as canopen does); this module makes the checks a real drive makes before a
download takes effect: access type, length, the file's LowLimit/HighLimit, supported
modes, scaling denominators, and the
CiA 301 rules for changing PDO communication and mapping objects (invalidate first,
sub-index 0 to 0 first, only mappable objects, at most 64 bits; 64 bytes for a drive on a
CAN FD bus, which maps PDOs as CANopen FD does).

A node may have up to eight CiA 402 axes (CiA 402-2): axis n's objects 0x6000-0x67FF are
at index + 0x800 (n - 1), in the same dictionary. Every service reads an axis's objects
through its ``AxisKeys`` (pre-built keys, as fast as a module constant), so one code serves
every axis; the communication objects (0x1000-0x1FFF) are the node's.
"""
from __future__ import annotations

import dataclasses
import logging
import struct
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from canopen import objectdictionary
from canopen.objectdictionary import datatypes
from canopen.sdo.constants import (
    ABORT_APPLICATION_DEVICE_STATE,
    ABORT_INVALID_VALUE,
    ABORT_LENGTH_NOT_MATCHED,
    ABORT_NO_SUBINDEX,
    ABORT_NOT_IN_OD,
    ABORT_PDO_CANNOT_MAP,
    ABORT_PDO_LENGTH_EXCEEDED,
    ABORT_READ_WRITEONLY,
    ABORT_VALUE_TOO_HIGH,
    ABORT_VALUE_TOO_LOW,
    ABORT_WRITE_READONLY,
)
from canopen.sdo.exceptions import SdoAbortedError

from ..commission.lss import UNCONFIGURED
from ..files.capabilities import modes_from_targets
from ..files.device_file import DeviceFileError, read_device_file
from ..files.identity import SUBINDEX, Identity, file_identity
from ..protocol import cia301 as c301
from ..protocol import cia402 as c
from ..protocol.cia301 import ObjectKey
from ..protocol.sdo_block_server import BlockUploadServer

PDO_NOT_VALID = 0x80000000

ERROR_REGISTER = (c301.ERROR_REGISTER, 0)
#: the factor group (axis 1's indices): an axis's joint units (state_machine.FactorGroup)
SCALING = {c.POSITION_ENCODER_RESOLUTION, c.GEAR_RATIO, c.RATED_TORQUE}
#: CiA 402-2: axis n's objects are axis 1's (0x6000-0x67FF) + AXIS_STRIDE (n - 1)
AXIS_STRIDE = 0x800
MAX_AXES = 8
_PROFILE_FIRST, _PROFILE_END = 0x6000, 0x6800


#: the first object a file's LowLimit/HighLimit is honoured for (0x1000..0x1FFF: CiA 301's)
_PROFILE_AREA = 0x2000

def axis_index(index: int, axis: int) -> int:
    """Axis ``axis``'s index of the CiA 402 object ``index`` (axis 1's); an index outside
    0x6000-0x67FF is the node's and the same for every axis."""
    if _PROFILE_FIRST <= index < _PROFILE_END:
        return index + AXIS_STRIDE * (axis - 1)
    return index


def axis_of(index: int, axes: int) -> tuple[int, int]:
    """(axis number, axis 1's index) of an object of a node with ``axes`` axes; (0, index)
    for an object of the node (or of an axis it does not have)."""
    offset = index - _PROFILE_FIRST
    if 0 <= offset < AXIS_STRIDE * axes:
        return offset // AXIS_STRIDE + 1, _PROFILE_FIRST + offset % AXIS_STRIDE
    return 0, index


def for_axes(values: Mapping[ObjectKey, Any], axes: int) -> dict[ObjectKey, Any]:
    """``values`` (axis 1's keys) with every CiA 402 object repeated for axes 2..``axes``."""
    out = dict(values)
    for axis in range(2, axes + 1):
        out.update(((axis_index(i, axis), s), v) for (i, s), v in values.items()
                   if _PROFILE_FIRST <= i < _PROFILE_END)
    return out


def axes_problem(od: objectdictionary.ObjectDictionary, axes: int) -> str | None:
    """Why a node of this file cannot have ``axes`` axes (None: it can): too many, or an
    axis whose controlword or statusword the file lacks."""
    if not 1 <= axes <= MAX_AXES:
        return f"a node has 1..{MAX_AXES} axes, got {axes}"
    for axis in range(2, axes + 1):  # axis 1's: the file as a master reads it
        for name, index in (("controlword", c.CONTROLWORD), ("statusword", c.STATUSWORD)):
            if axis_index(index, axis) not in od:
                return (f"axis {axis} needs its {name} 0x{axis_index(index, axis):04X}, "
                        "which the device file lacks")
    return None


@dataclass(frozen=True, slots=True)
class AxisKeys:
    """The keys of one axis's CiA 402 objects in the node's ``values``, built once: a key
    built per access costs as much as the read, and the state machine reads them every
    SYNC."""
    number: int
    controlword: ObjectKey
    statusword: ObjectKey
    mode: ObjectKey
    mode_display: ObjectKey
    supported_modes: ObjectKey
    position: ObjectKey
    velocity: ObjectKey
    torque: ObjectKey
    error_code: ObjectKey
    max_torque: ObjectKey
    interpolation_target: ObjectKey
    target_position: ObjectKey
    target_velocity: ObjectKey
    target_torque: ObjectKey
    velocity_offset: ObjectKey
    torque_offset: ObjectKey
    profile_velocity: ObjectKey
    homing_method: ObjectKey
    home_offset: ObjectKey
    abort_connection_option: ObjectKey
    quick_stop_option: ObjectKey
    shutdown_option: ObjectKey
    disable_operation_option: ObjectKey
    quick_stop_deceleration: ObjectKey
    resolution_increments: ObjectKey  # 0x608F:1 / :2
    resolution_revolutions: ObjectKey
    gear_motor: ObjectKey             # 0x6091:1 / :2
    gear_shaft: ObjectKey
    rated_torque: ObjectKey
    position_limit_min: ObjectKey     # 0x607D:1 / :2
    position_limit_max: ObjectKey
    max_profile_velocity: ObjectKey
    max_motor_speed: ObjectKey
    following_error_window: ObjectKey
    following_error_timeout: ObjectKey

    @classmethod
    def of(cls, axis: int) -> AxisKeys:
        """Axis ``axis`` (1..MAX_AXES) of a node."""
        if not 1 <= axis <= MAX_AXES:
            raise ValueError(f"a CiA 402 axis is 1..{MAX_AXES}, got {axis}")

        def key(index: int, subindex: int = 0) -> ObjectKey:
            return axis_index(index, axis), subindex

        return cls(
            number=axis, controlword=key(c.CONTROLWORD), statusword=key(c.STATUSWORD),
            mode=key(c.MODES_OF_OPERATION), mode_display=key(c.MODES_OF_OPERATION_DISPLAY),
            supported_modes=key(c.SUPPORTED_DRIVE_MODES), position=key(c.POSITION_ACTUAL),
            velocity=key(c.VELOCITY_ACTUAL), torque=key(c.TORQUE_ACTUAL),
            error_code=key(c.ERROR_CODE), max_torque=key(c.MAX_TORQUE),
            interpolation_target=key(c.INTERPOLATION_DATA, 1),
            target_position=key(c.TARGET_POSITION), target_velocity=key(c.TARGET_VELOCITY),
            target_torque=key(c.TARGET_TORQUE), velocity_offset=key(c.VELOCITY_OFFSET),
            torque_offset=key(c.TORQUE_OFFSET), profile_velocity=key(c.PROFILE_VELOCITY),
            homing_method=key(c.HOMING_METHOD), home_offset=key(c.HOME_OFFSET),
            abort_connection_option=key(c.ABORT_CONNECTION_OPTION),
            quick_stop_option=key(c.QUICK_STOP_OPTION),
            shutdown_option=key(c.SHUTDOWN_OPTION),
            disable_operation_option=key(c.DISABLE_OPERATION_OPTION),
            quick_stop_deceleration=key(c.QUICK_STOP_DECELERATION),
            resolution_increments=key(c.POSITION_ENCODER_RESOLUTION, 1),
            resolution_revolutions=key(c.POSITION_ENCODER_RESOLUTION, 2),
            gear_motor=key(c.GEAR_RATIO, 1), gear_shaft=key(c.GEAR_RATIO, 2),
            rated_torque=key(c.RATED_TORQUE),
            position_limit_min=key(c.SOFTWARE_POSITION_LIMIT, 1),
            position_limit_max=key(c.SOFTWARE_POSITION_LIMIT, 2),
            max_profile_velocity=key(c.MAX_PROFILE_VELOCITY),
            max_motor_speed=key(c.MAX_MOTOR_SPEED),
            following_error_window=key(c.FOLLOWING_ERROR_WINDOW),
            following_error_timeout=key(c.FOLLOWING_ERROR_TIMEOUT))


class _SdoLink:
    """What canopen's SdoServer needs of a network: a way to send its responses."""

    def __init__(self, send: Callable[[int, bytes], None]) -> None:
        self._send = send

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._send(can_id, bytes(data))


class ObjectDictionaryServer:
    """The drive's objects and the SDO server on them.

    ``on_write(key, value)`` runs after every accepted SDO download, so the drive can make
    the write take effect (a controlword transition, a new heartbeat period, new PDOs).
    ``axes``: the node's axes, whose writes are checked as their own (mode, scaling).
    ``pdo_bytes``: the longest PDO a mapping may make (8; 64 on a CAN FD bus).
    """

    def __init__(self, od: objectdictionary.ObjectDictionary, node_id: int,
                 send: Callable[[int, bytes], None],
                 on_write: Callable[[ObjectKey, Any], None],
                 fallbacks: Mapping[ObjectKey, Any] | None,
                 axes: Sequence[AxisKeys], pdo_bytes: int = 8) -> None:
        self.object_dictionary = od  # the name canopen's SdoServer reads
        self._node_id = node_id
        self._pdo_bits = 8 * pdo_bytes
        self._on_write = on_write
        self._axes = tuple(axes)
        # What the drive does for objects its file lacks or lists without a value (never
        # visible on the bus for a missing one: SDO and PDO mapping look the object up in
        # the file first), then the file's values (a DCF's ParameterValue over
        # DefaultValue). An object with no value and no plausible stand-in reads 0.
        self.defaults: dict[ObjectKey, Any] = dict(fallbacks or {})
        #: objects the file lists without a value, answered with a stand-in (``assumed``)
        self.assumed: dict[ObjectKey, Any] = {}
        for obj in od.values():
            members = [obj] if isinstance(obj, objectdictionary.ODVariable) else obj.values()
            for var in members:
                key = (var.index, var.subindex)
                value = var.value if var.value is not None else var.default
                if value is not None:
                    self.defaults[key] = value
                elif key in self.defaults:
                    self.assumed[key] = self.defaults[key]
                else:
                    self.defaults[key] = _empty(var.data_type)
        #: default PDO mappings naming an object the file does not describe (or cannot be
        #: a PDO's): mapping index -> that entry; the drive starts with the PDO unmapped
        self.unmapped: dict[int, str] = {}
        self._unmap_undescribed_defaults()
        self.values: dict[ObjectKey, Any] = dict(self.defaults)
        self._sdo = BlockUploadServer(c301.SDO_RX + node_id, c301.SDO_TX + node_id, self)
        self._sdo.network = _SdoLink(send)  # type: ignore[assignment]  # send_message only

    def _unmap_undescribed_defaults(self) -> None:
        """A file's default mapping may name an object the file does not list (or one of a
        type no PDO carries): the real drive has it, this simulation cannot emulate it. That
        PDO starts unmapped (0 objects), as if its drive had been cleared; a master remaps a
        writable mapping at bring-up anyway (a fixed one naming it is refused by planning)."""
        for index in (*range(0x1600, 0x1604), *range(0x1A00, 0x1A04)):
            count = self.defaults.get((index, 0))
            if not isinstance(count, int) or count <= 0:
                continue
            for sub in range(1, count + 1):
                entry = self.defaults.get((index, sub))
                try:
                    if not isinstance(entry, int):
                        raise SdoAbortedError(ABORT_NO_SUBINDEX)
                    var = self.var(entry >> 16, (entry >> 8) & 0xFF)
                except SdoAbortedError:
                    var = None
                if var is None or var.data_type is None \
                        or not isinstance(var.STRUCT_TYPES.get(var.data_type), struct.Struct):
                    self.defaults[(index, 0)] = 0
                    self.unmapped[index] = (f"0x{entry >> 16:04X}:{(entry >> 8) & 0xFF}"
                                            if isinstance(entry, int) else f"sub-index {sub}")
                    break

    def request(self, data: bytes) -> None:
        """One SDO request frame from a client."""
        self._sdo.on_request(c301.SDO_RX + self._node_id, data, 0.0)

    def reset_all(self) -> None:
        """Reset node: every object to its default (in place: the services hold ``values``)."""
        self.values.clear()
        self.values.update(self.defaults)

    def reset_communication(self) -> None:
        """Reset communication: the communication area (0x1000-0x1FFF) to defaults, except
        the error register and error history, which belong to the device."""
        for key, value in self.defaults.items():
            if 0x1000 <= key[0] < 0x2000 \
                    and key[0] not in (c301.ERROR_REGISTER, c301.PREDEFINED_ERROR_FIELD):
                self.values[key] = value

    def mode_supported(self, mode: int, axis: AxisKeys) -> bool:
        """Mode 0 (none) or a mode whose bit is set in the axis's 0x6502."""
        supported = self.values[axis.supported_modes]
        return mode == 0 or (0 < mode <= 32 and bool(supported >> (mode - 1) & 1))

    def var(self, index: int, subindex: int) -> objectdictionary.ODVariable:
        obj = self.object_dictionary.get(index)
        if obj is None:
            raise SdoAbortedError(ABORT_NOT_IN_OD)
        if isinstance(obj, objectdictionary.ODVariable):
            if subindex != 0:
                raise SdoAbortedError(ABORT_NO_SUBINDEX)
            return obj
        if subindex not in obj:
            raise SdoAbortedError(ABORT_NO_SUBINDEX)
        var: objectdictionary.ODVariable = obj[subindex]
        return var

    # ------------------------------------------------------------------ SdoServer hooks
    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        """canopen SdoServer hook: upload."""
        var = self.var(index, subindex)
        if check_readable and not var.readable:
            raise SdoAbortedError(ABORT_READ_WRITEONLY)
        value = self.values[(var.index, var.subindex)]
        return var.encode_raw(value)

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        """canopen SdoServer hook: download, with the checks a real drive makes."""
        var = self.var(index, subindex)
        if check_writable and not var.writable:
            raise SdoAbortedError(ABORT_WRITE_READONLY)
        if var.data_type in objectdictionary.NUMBER_TYPES and 8 * len(data) != len(var):
            raise SdoAbortedError(ABORT_LENGTH_NOT_MATCHED)
        value = var.decode_raw(bytes(data))
        # The file's HighLimit / LowLimit, on the device profile's objects: a communication
        # object's layout is CiA 301's (0x1016's producer node id in bits 16..23), and files
        # that limit one as if it were a plain number (Elmo's 0x1016:1 HighLimit=65535) are
        # wrong about the devices, which take the standard values.
        if isinstance(value, (int, float)) and var.index >= _PROFILE_AREA:
            if var.max is not None and value > var.max:
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
            if var.min is not None and value < var.min:
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
        key = (var.index, var.subindex)
        self._check_write(key, value)
        self.values[key] = value
        self._on_write(key, value)

    # ------------------------------------------------------------------ write checks
    def _check_write(self, key: ObjectKey, value: Any) -> None:
        index, sub = key
        axis, base = axis_of(index, len(self._axes))
        if base == c.MODES_OF_OPERATION and sub == 0 \
                and not self.mode_supported(value, self._axes[axis - 1]):
            raise SdoAbortedError(ABORT_INVALID_VALUE)
        if base in SCALING and value == 0 and (base == c.RATED_TORQUE or sub > 0):
            raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
        if key == (c301.PREDEFINED_ERROR_FIELD, 0) and value != 0:
            raise SdoAbortedError(ABORT_INVALID_VALUE)
        if 0x1400 <= index <= 0x1403 or 0x1800 <= index <= 0x1803:
            if sub == 1:
                current = self.values[key]
                if not current & PDO_NOT_VALID and not value & PDO_NOT_VALID \
                        and (current ^ value) & 0x7FF:
                    raise SdoAbortedError(ABORT_INVALID_VALUE)  # CiA 301: invalidate first
                if value & 0x3FFFF800:  # 11-bit identifiers only
                    raise SdoAbortedError(ABORT_INVALID_VALUE)
            return
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            comm = index - 0x200
            if not self.values[(comm, 1)] & PDO_NOT_VALID:
                raise SdoAbortedError(ABORT_APPLICATION_DEVICE_STATE)  # mapping of a valid PDO
            if sub == 0:
                self._check_mapping(index, value, tx=index >= 0x1A00)
            elif self.values[(index, 0)] != 0:
                raise SdoAbortedError(ABORT_APPLICATION_DEVICE_STATE)  # sub 0 must be 0 first

    def _check_mapping(self, map_index: int, count: int, tx: bool) -> None:
        if count > 8:
            raise SdoAbortedError(ABORT_INVALID_VALUE)
        bits = 0
        for sub in range(1, count + 1):
            entry = self.values[(map_index, sub)]
            index, subindex, length = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            var = self.var(index, subindex)
            if not var.pdo_mappable or var.data_type not in objectdictionary.NUMBER_TYPES \
                    or not isinstance(var.STRUCT_TYPES.get(var.data_type), struct.Struct) \
                    or not (var.readable if tx else var.writable) \
                    or length != len(var):
                raise SdoAbortedError(ABORT_PDO_CANNOT_MAP)
            bits += length
        if bits > self._pdo_bits:
            raise SdoAbortedError(ABORT_PDO_LENGTH_EXCEEDED)


def _empty(data_type: int | None) -> Any:
    if data_type in (datatypes.VISIBLE_STRING, datatypes.UNICODE_STRING):
        return ""
    if data_type in (datatypes.OCTET_STRING, datatypes.DOMAIN):
        return b""
    return 0


#: The modes this simulator implements (0x6502 bits): a file without 0x6502 gets these.
IMPLEMENTED_MODES = sum(1 << (m - 1) for m in (
    c.Mode.PROFILE_POSITION, c.Mode.PROFILE_VELOCITY, c.Mode.HOMING, c.Mode.INTERPOLATED_POSITION,
    c.Mode.CSP, c.Mode.CSV, c.Mode.CST))
#: 0x1000 of a drive (CiA 402 profile; servo drive additional information)
CIA402_DEVICE_TYPE = 0x0002_0192


def fallback_values(increments_per_rev: int, rated_torque_nm: float,
                    od: objectdictionary.ObjectDictionary | None = None) -> dict[ObjectKey, Any]:
    """How a simulated drive behaves where its file has no object, or lists one without a
    value: scaling as given (the config's numbers, factors 1:1), no reaction to a lost
    connection without 0x6007 (no CiA 402 reaction at all: the honest emulation of a drive
    that cannot be told one), the generic option codes, no torque limit without 0x6072, no
    offsets; a CiA 402 servo's 0x1000, and the modes its target objects imply (``od``, of
    those this simulator implements)."""
    modes = IMPLEMENTED_MODES
    if od is not None:
        modes &= modes_from_targets(od) or IMPLEMENTED_MODES
    return {
        (c301.DEVICE_TYPE, 0): CIA402_DEVICE_TYPE,
        (c.POSITION_ENCODER_RESOLUTION, 1): increments_per_rev,
        (c.POSITION_ENCODER_RESOLUTION, 2): 1,
        (c.GEAR_RATIO, 1): 1, (c.GEAR_RATIO, 2): 1,
        (c.RATED_TORQUE, 0): max(1, round(rated_torque_nm * 1000)),
        (c.ABORT_CONNECTION_OPTION, 0): c.AbortConnectionOption.NONE,
        (c.QUICK_STOP_OPTION, 0): 2, (c.SHUTDOWN_OPTION, 0): 0,
        (c.DISABLE_OPERATION_OPTION, 0): 1,
        (c.QUICK_STOP_DECELERATION, 0): 10 * increments_per_rev,
        (c.MAX_TORQUE, 0): 0x7FFF,
        (c.VELOCITY_OFFSET, 0): 0, (c.TORQUE_OFFSET, 0): 0,
        (c.TARGET_POSITION, 0): 0, (c.TARGET_VELOCITY, 0): 0, (c.TARGET_TORQUE, 0): 0,
        (c.INTERPOLATION_DATA, 1): 0,
        (c.HOMING_METHOD, 0): 35, (c.HOME_OFFSET, 0): 0,  # 35: on the current position
        (c.PROFILE_VELOCITY, 0): increments_per_rev,  # one motor turn per second
        (c.SUPPORTED_DRIVE_MODES, 0): modes,
        (c.ERROR_CODE, 0): 0, (c301.ERROR_BEHAVIOR, 1): 1,
        (c301.PRODUCER_HEARTBEAT_TIME, 0): 0,
    }


def log_file_notes(log: logging.Logger, eds: str, objects: ObjectDictionaryServer) -> None:
    """What a segment's drives (all made from ``eds``, ``objects`` one's) answer where the
    file gives no value, and which default PDO mapping names an object it lacks: once, on
    the segment's ``log``."""
    assumed = objects.assumed
    if assumed:
        log.info("simulated drives of %s: where the file gives no value they answer %s",
                 eds, ", ".join(f"0x{i:04X}:{s} = {v if v < 10 else hex(v)}"
                                for (i, s), v in sorted(assumed.items())
                                if isinstance(v, int) and not 0x2000 <= i < 0x6000))
    if objects.unmapped:
        log.warning("simulated drives of %s: the file's default mapping of %s names an "
                    "object it does not describe: that PDO starts unmapped", eds,
                    ", ".join(f"0x{i:04X} ({entry})"
                              for i, entry in sorted(objects.unmapped.items())))


def load_object_dictionaries(eds_path: str, node_ids: Iterable[int]
                             ) -> dict[int, objectdictionary.ObjectDictionary]:
    """Each drive's object dictionary from one EDS/DCF (the file read once), read as the
    master reads it (device_file.py: the same repairs, the same one-line refusal)."""
    ids = list(node_ids)
    try:
        device = read_device_file(str(eds_path))
        return {n: device.object_dictionary(n) for n in ids}
    except DeviceFileError as exc:
        raise ValueError(f"simulated drive {ids[0] if len(ids) == 1 else ids}: {exc}") \
            from None


def load_object_dictionary(eds_path: str, node_id: int) -> objectdictionary.ObjectDictionary:
    """One drive's object dictionary (``load_object_dictionaries`` for one node)."""
    return load_object_dictionaries(eds_path, [node_id])[node_id]


def own_identity(od: objectdictionary.ObjectDictionary, node_id: int,
                 overrides: Mapping[ObjectKey, Any], given: Identity | None) -> Identity:
    """A node's 0x1018: the file's (a subindex it lists without a value: 0, as the drive
    answers it), with the vendor and product its [DeviceInfo] names where it names a vendor
    (what bring-up holds a drive to without ``identity:``: identity.file_identity), a
    serial number of its own so that each node is one of a kind
    (the file's plus node id - 1, or the node id where the file gives none), then
    ``overrides`` and ``given``."""
    values: dict[str, int | None] = {}
    made_for = file_identity(od)
    for name, sub in SUBINDEX.items():
        variable = od.get_variable(c301.IDENTITY, sub)
        stated = getattr(made_for, name, None) if made_for.vendor_id is not None else None
        if variable is None:
            listed = None
        elif stated is not None:
            listed = stated
        else:  # listed without a value: what the drive answers for it (DriveObjects), 0
            listed = variable.default if variable.default is not None \
                else _empty(variable.data_type)
        values[name] = overrides.get((c301.IDENTITY, sub), listed)
    if node_id != UNCONFIGURED and not (overrides.get((c301.IDENTITY, SUBINDEX["serial"]))):
        # one file, many simulated nodes: each a device of its own (an LSS address, a
        # serial bring-up may hold it to). A file's serial (a DCF read off one device) is
        # node 1's, the next node's one more; no serial in the file: the node id.
        values["serial"] = ((values["serial"] + node_id - 1) & 0xFFFF_FFFF if values["serial"]
                            else node_id)
    return dataclasses.replace(Identity(**values), **{
        name: value for name, value in dataclasses.asdict(given or Identity()).items()
        if value is not None})
