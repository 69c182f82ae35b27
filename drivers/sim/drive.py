"""One simulated CiA 402 servo drive, as seen from the CAN bus.

It behaves like a real drive where a master can tell the difference: boot-up and NMT,
heartbeat producer and consumer with the 0x6007 reaction, an SDO server on the EDS (PDO
mapping and communication objects written by SDO take effect, with the CiA 301 rules for
changing them), synchronous and event-driven TPDOs, RPDOs only in OPERATIONAL, the complete
CiA 402 state machine with quick stop, fault reaction and fault reset, CSP/CSV/CST, EMCY,
and an STO input. Faults can be injected to test a master's supervision.

A drive never owns a thread or a socket: its SimulatedSegment feeds it frames and timer
events with the segment lock held, and sends what it transmits.
"""
from __future__ import annotations

import math
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass
from operator import itemgetter
from typing import Any, Protocol

import canopen
import numpy as np
from canopen import objectdictionary
from canopen.sdo.constants import (
    ABORT_APPLICATION_DEVICE_STATE,
    ABORT_INVALID_VALUE,
    ABORT_LENGTH_NOT_MATCHED,
    ABORT_NO_SUBINDEX,
    ABORT_NOT_IN_OD,
    ABORT_PDO_CANNOT_MAP,
    ABORT_PDO_LENGTH_EXCEEDED,
    ABORT_READ_WRITEONLY,
    ABORT_VALUE_TOO_LOW,
    ABORT_WRITE_READONLY,
)
from canopen.sdo.exceptions import SdoAbortedError
from canopen.sdo.server import SdoServer

from .. import cia301 as c301
from .. import cia402 as c
from ..cia301 import NmtCommand, NmtState
from ..cia402 import State402
from .dynamics import JointDynamics, LoopMode


class Segment(Protocol):
    """What a drive needs from the bus segment it sits on (segment.SimulatedSegment): a
    drive owns no thread and no socket, so this is its whole view of the world, and the
    drive module does not import the segment module."""
    lock: threading.RLock
    rng: np.random.Generator
    dynamics: JointDynamics

    def clock(self) -> float: ...
    def schedule(self, when: float, fn: Callable[..., Any], *args: Any) -> None: ...
    def send(self, cob_id: int, data: bytes) -> None: ...
    def judge_at(self, deadline: float) -> float | None: ...
    def set_rpdo_routes(self, drive: SimulatedDrive, routes: dict[int, Any]) -> None: ...


PDO_NOT_VALID = 0x80000000
Key = tuple[int, int]

CONTROLWORD = (c.CONTROLWORD, 0)
STATUSWORD = (c.STATUSWORD, 0)
MODE = (c.MODES_OF_OPERATION, 0)
MODE_DISPLAY = (c.MODES_OF_OPERATION_DISPLAY, 0)
POSITION = (c.POSITION_ACTUAL, 0)
VELOCITY = (c.VELOCITY_ACTUAL, 0)
TORQUE = (c.TORQUE_ACTUAL, 0)
ERROR_CODE = (c.ERROR_CODE, 0)
ERROR_REGISTER = (c301.ERROR_REGISTER, 0)

# States in which the power stage is on (the loops may produce torque).
POWERED = (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE,
           State402.FAULT_REACTION_ACTIVE)
# States left for switch on disabled when STO goes low or on "disable voltage".
VOLTAGE_STATES = (State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON,
                  State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE)
SCALING = {c.POSITION_ENCODER_RESOLUTION, c.GEAR_RATIO, c.RATED_TORQUE}

# Error register (0x1001) bit per EMCY error class (code >> 12), CiA 301.
ERROR_REGISTER_BIT = {0x2: 1 << 1, 0x3: 1 << 2, 0x4: 1 << 3, 0x8: 1 << 4}
# A ramp has ended once its command is zero and the joint is slower than this, or after
# its command has been zero this long (standstill window and time of a real drive).
STOPPED_VELOCITY = 0.01  # rad/s
STANDSTILL_TIME = 0.05  # s


def _wrap(value: float, bits: int) -> int:
    """Integer actual values overflow like a drive's counters do."""
    half = 1 << (bits - 1)
    return (int(round(value)) + half) % (1 << bits) - half


def _clamp(value: float, bits: int) -> int:
    half = 1 << (bits - 1)
    return max(-half, min(half - 1, int(round(value))))


@dataclass
class _Pdo:
    """One PDO as configured in the OD, compiled for struct packing."""
    number: int
    cob_id: int
    valid: bool
    trans_type: int
    keys: tuple[Key, ...]
    layout: struct.Struct
    values_of: Callable[[dict[Key, Any]], tuple[Any, ...]]
    counter: int = 0
    last: bytes | None = None      # event-driven TPDO: what was sent last
    pending: bytes | None = None   # synchronous RPDO: received, applied at the next SYNC


class _SdoLink:
    """What canopen's SdoServer needs of a network: a way to send its responses."""

    def __init__(self, drive: SimulatedDrive) -> None:
        self._drive = drive

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._drive._tx(can_id, bytes(data))


class SimulatedDrive:
    """A CiA 402 servo drive on a SimulatedSegment; use ``segment.drives[node_id]``.

    Properties are safe to read from any thread; the fault-injection methods take the
    segment lock.
    """

    def __init__(self, segment: Segment, node_id: int, joint: int,
                 object_dictionary: objectdictionary.ObjectDictionary) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CANopen node id must be 1..127, got {node_id}")
        self.node_id = node_id
        self.joint = joint
        self.object_dictionary = object_dictionary  # the name canopen's SdoServer reads
        self._seg = segment
        self._dyn = segment.dynamics
        self._sdo = SdoServer(c301.SDO_RX + node_id, c301.SDO_TX + node_id, self)
        self._sdo.network = _SdoLink(self)  # type: ignore[assignment]  # send_message only
        self._defaults: dict[Key, Any] = {}
        for obj in object_dictionary.values():
            members = [obj] if isinstance(obj, objectdictionary.ODVariable) else obj.values()
            for var in members:
                value = var.value if var.value is not None else var.default
                self._defaults[(var.index, var.subindex)] = value
        self._values: dict[Key, Any] = dict(self._defaults)
        self._nmt = NmtState.BOOT_UP
        self._state = State402.NOT_READY_TO_SWITCH_ON
        self._last_controlword = 0
        self._error_register = 0
        self._errors: list[int] = []  # 0x1003 history, newest first
        # ramps (quick stop, halt, fault reaction, shutdown/disable operation option 1)
        self._ramping = False
        self._ramp_velocity = 0.0
        self._ramp_decel = 0.0
        self._ramp_then: State402 | None = None
        self._ramp_zero_time = 0.0
        # heartbeat producer and consumer
        self._hb_generation = 0
        self._consumer_generation = 0
        self._consumers: dict[int, float] = {}
        self._hb_deadline: dict[int, float] = {}
        self._hb_armed: set[int] = set()
        self._hb_lost: set[int] = set()
        # PDOs
        self._tpdos: list[_Pdo] = []
        self._rpdos: list[_Pdo] = []
        self._event_tpdos: list[_Pdo] = []
        # scaling, from the OD
        self._inc_per_rad = 1.0
        self._nm_per_permille = 1.0
        # injected faults and inputs
        self._silent = False
        self._statusword_xor = 0
        self._answer_sync = True
        self._tpdo_delay = 0.0
        self._sto_low = False
        self._position_noise = 0.0
        self._babble_left = 0

    # ------------------------------------------------------------------ read-only view
    @property
    def nmt_state(self) -> NmtState:
        return self._nmt

    @property
    def state402(self) -> State402:
        return self._state

    @property
    def statusword(self) -> int:
        return int(self._values[STATUSWORD])

    @property
    def controlword(self) -> int:
        return int(self._values[CONTROLWORD])

    @property
    def mode_display(self) -> int:
        return int(self._values[MODE_DISPLAY])

    @property
    def error_code(self) -> int:
        return int(self._values[ERROR_CODE])

    @property
    def error_register(self) -> int:
        return self._error_register

    @property
    def position_increments(self) -> int:
        return int(self._values[POSITION])

    @property
    def velocity_increments(self) -> int:
        return int(self._values[VELOCITY])

    @property
    def torque_per_mille(self) -> int:
        return int(self._values[TORQUE])

    @property
    def position_rad(self) -> float:
        """True joint position (no sensor noise)."""
        return float(self._dyn.position[self.joint])

    @property
    def velocity_rad_s(self) -> float:
        return float(self._dyn.velocity[self.joint])

    @property
    def torque_nm(self) -> float:
        """Joint torque the power stage applied in the last step."""
        return float(self._dyn.torque[self.joint])

    @property
    def increments_per_rad(self) -> float:
        """Joint radians to position increments (0x608F and 0x6091)."""
        return self._inc_per_rad

    @property
    def nm_per_permille(self) -> float:
        """Joint torque of one per mille of rated torque (0x6076, gear ratio)."""
        return self._nm_per_permille

    @property
    def sto_low(self) -> bool:
        return self._sto_low

    def od_value(self, index: int, subindex: int = 0) -> Any:
        """Current value of an object, as the SDO server would return it."""
        return self._values[(index, subindex)]

    def status_line(self) -> str:
        try:
            mode = c.Mode(self.mode_display).name
        except ValueError:
            mode = str(self.mode_display)
        flags = "".join((" STO" if self._sto_low else "", " SILENT" if self._silent else "",
                         " NO-SYNC" if not self._answer_sync else ""))
        return (f"node {self.node_id:3d} {self._nmt.name:15s} {self._state.name:22s} "
                f"sw=0x{self.statusword:04X} mode={mode:4s} pos={self.position_rad:+9.4f} rad "
                f"vel={self.velocity_rad_s:+9.4f} rad/s torque={self.torque_nm:+7.3f} Nm "
                f"err=0x{self.error_code:04X}{flags}")

    # ------------------------------------------------------------------ fault injection
    def trip_fault(self, code: int = c301.EMCY_GENERIC) -> None:
        """An internal fault: EMCY with ``code``, fault reaction, then FAULT."""
        if not 0 < code <= 0xFFFF:
            raise ValueError(f"EMCY error code must be 0x0001..0xFFFF, got 0x{code:X}")
        with self._seg.lock:
            self._fault(code)
            self._emit_event_tpdos()

    def garble_statusword(self, xor: int = 0x0008) -> None:
        """Every statusword this drive reports (TPDO, SDO) is XORed with ``xor`` from now on
        (0 = healthy again): a bit error in firmware. The default flips the fault bit, which
        makes switch on disabled, ready to switch on and switched on read as no CiA 402
        state, and operation enabled as fault reaction active."""
        with self._seg.lock:
            self._values[STATUSWORD] ^= self._statusword_xor ^ xor
            self._statusword_xor = xor

    def set_silent(self, silent: bool = True) -> None:
        """Transmit nothing at all (heartbeat, TPDO, EMCY, SDO), like a dead TX line.
        The drive keeps receiving and keeps following its targets."""
        with self._seg.lock:
            self._silent = bool(silent)

    def set_sync_response(self, answer: bool) -> None:
        """False: ignore SYNC (no synchronous TPDOs, synchronous RPDOs not applied)."""
        with self._seg.lock:
            self._answer_sync = bool(answer)

    def set_tpdo_delay(self, seconds: float) -> None:
        """Send every TPDO this late (0 = at once)."""
        if not 0 <= seconds <= 10:
            raise ValueError(f"TPDO delay must be 0..10 s, got {seconds}")
        with self._seg.lock:
            self._tpdo_delay = float(seconds)

    def set_sto(self, low: bool) -> None:
        """STO input low: the power stage is off and the drive holds in switch on disabled
        (EMCY EMCY_STO, warning bit); back high: EMCY 0x0000, the drive may be enabled."""
        with self._seg.lock:
            self._set_sto(bool(low))
            self._emit_event_tpdos()

    def set_position_noise(self, std_increments: float) -> None:
        """Gaussian noise (standard deviation, increments) on the reported 0x6064."""
        if std_increments < 0:
            raise ValueError(f"noise must be >= 0, got {std_increments}")
        with self._seg.lock:
            self._position_noise = float(std_increments)

    def babble(self, count: int = 1000, cob_id: int = 0x001, data: bytes = bytes(8),
               burst: int = 50) -> None:
        """Flood the bus with ``count`` frames of ``cob_id`` (a babbling node), ``burst``
        frames per millisecond, from the segment's timer thread. Bounded: at most 100000."""
        if not 1 <= count <= 100_000 or not 0 <= cob_id <= 0x7FF or len(data) > 8 or burst < 1:
            raise ValueError(f"babble: count 1..100000, cob_id 0..0x7FF, data <= 8 bytes, "
                             f"burst >= 1; got {count}, 0x{cob_id:X}, {len(data)}, {burst}")
        with self._seg.lock:
            running = self._babble_left > 0  # one flood at a time: a new call resets its count
            self._babble_left = count
            if not running:
                self._seg.schedule(self._seg.clock(), self._babble_burst, cob_id, bytes(data),
                                   burst)

    # ------------------------------------------------------------------ power-up and NMT
    def power_on(self) -> None:
        """Power-on / reset node: whole OD to defaults, CiA 402 state machine restarts."""
        self._values = dict(self._defaults)
        self._errors.clear()
        self._error_register = 1 if self._sto_low else 0
        self._last_controlword = 0
        self._ramping = False
        self._state = State402.NOT_READY_TO_SWITCH_ON
        self._update_scales()
        self._set_state(State402.SWITCH_ON_DISABLED)  # transition 1, automatic
        self._sample()
        self._reset_communication()

    def _reset_communication(self) -> None:
        """Communication objects to defaults, then boot-up and PRE-OPERATIONAL."""
        for key, value in self._defaults.items():
            if 0x1000 <= key[0] < 0x2000 \
                    and key[0] not in (c301.ERROR_REGISTER, c301.PREDEFINED_ERROR_FIELD):
                self._values[key] = value
        self._nmt = NmtState.BOOT_UP
        self._tx(c301.HEARTBEAT + self.node_id, b"\x00")
        self._nmt = NmtState.PRE_OPERATIONAL
        self._build_pdos()
        self._load_consumers()
        self._start_heartbeat()

    def on_nmt(self, command: int) -> None:
        if command == NmtCommand.START:
            self._build_pdos()
            self._nmt = NmtState.OPERATIONAL
        elif command == NmtCommand.STOP:
            self._nmt = NmtState.STOPPED
            self._abort_connection(c301.EMCY_HEARTBEAT)
        elif command == NmtCommand.PRE_OPERATIONAL:
            self._nmt = NmtState.PRE_OPERATIONAL
        elif command == NmtCommand.RESET_NODE:
            self.power_on()
        elif command == NmtCommand.RESET_COMMUNICATION:
            self._abort_connection(c301.EMCY_HEARTBEAT)
            self._reset_communication()
        self._emit_event_tpdos()

    # ------------------------------------------------------------------ heartbeat
    def _start_heartbeat(self) -> None:
        self._hb_generation += 1
        period_ms = self._values[(c301.PRODUCER_HEARTBEAT_TIME, 0)]
        if period_ms:
            due = self._seg.clock() + period_ms / 1000.0
            self._seg.schedule(due, self._heartbeat_tick, self._hb_generation, due)

    def _heartbeat_tick(self, generation: int, due: float) -> None:
        if generation != self._hb_generation:
            return
        self._tx(c301.HEARTBEAT + self.node_id, bytes((self._nmt,)))
        period = self._values[(c301.PRODUCER_HEARTBEAT_TIME, 0)] / 1000.0
        nxt = due + period
        now = self._seg.clock()
        if nxt <= now:  # fell behind (loaded machine): no burst of catch-up heartbeats
            nxt = now + period
        self._seg.schedule(nxt, self._heartbeat_tick, generation, nxt)

    def _load_consumers(self) -> None:
        self._consumer_generation += 1
        self._consumers.clear()
        self._hb_armed.clear()
        self._hb_lost.clear()
        count = self._values.get((c301.CONSUMER_HEARTBEAT_TIME, 0), 0)
        for sub in range(1, count + 1):
            entry = self._values[(c301.CONSUMER_HEARTBEAT_TIME, sub)]
            node, ms = (entry >> 16) & 0xFF, entry & 0xFFFF
            if node and ms:
                self._consumers[node] = ms / 1000.0

    def on_heartbeat(self, node: int, arrived: float) -> None:
        period = self._consumers.get(node)
        if period is None:
            return
        self._hb_deadline[node] = arrived + period
        if node in self._hb_lost:
            self._hb_lost.discard(node)
            if not self._errors_active():
                self._error_register = 0
                self._emcy(c301.EMCY_NO_ERROR)
        if node not in self._hb_armed:  # monitoring starts with the first heartbeat
            self._hb_armed.add(node)
            self._seg.schedule(arrived + period, self._heartbeat_check, node,
                               self._consumer_generation)

    def _heartbeat_check(self, node: int, generation: int) -> None:
        if generation != self._consumer_generation or node not in self._hb_armed:
            return
        deadline = self._hb_deadline[node]
        later = self._seg.judge_at(deadline)
        if later is not None:  # a heartbeat that came in time may still be queued
            self._seg.schedule(later, self._heartbeat_check, node, generation)
            return
        self._hb_armed.discard(node)
        self._hb_lost.add(node)
        self._heartbeat_lost()

    def _heartbeat_lost(self) -> None:
        option = self._values[(c.ABORT_CONNECTION_OPTION, 0)]
        if option != c.AbortConnectionOption.FAULT:  # the fault sends its own EMCY
            self._error_register |= 1 | ERROR_REGISTER_BIT[0x8]
            self._record_error(c301.EMCY_HEARTBEAT)
            self._emcy(c301.EMCY_HEARTBEAT)
        behaviour = self._values.get((c301.ERROR_BEHAVIOR, 1), 1)
        if behaviour == 0 and self._nmt == NmtState.OPERATIONAL:
            self._nmt = NmtState.PRE_OPERATIONAL
        elif behaviour == 2:
            self._nmt = NmtState.STOPPED
        self._abort_connection(c301.EMCY_HEARTBEAT)
        self._emit_event_tpdos()

    def _abort_connection(self, code: int) -> None:
        """0x6007 reaction to heartbeat loss, NMT stop or reset communication."""
        option = self._values[(c.ABORT_CONNECTION_OPTION, 0)]
        if option == c.AbortConnectionOption.FAULT:
            if self._state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                self._fault(code)
        elif option == c.AbortConnectionOption.DISABLE_VOLTAGE:
            if self._state in VOLTAGE_STATES:
                self._set_state(State402.SWITCH_ON_DISABLED)
        elif option == c.AbortConnectionOption.QUICK_STOP:
            if self._state == State402.OPERATION_ENABLED:
                self._quick_stop()
            elif self._state in (State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON):
                self._set_state(State402.SWITCH_ON_DISABLED)

    # ------------------------------------------------------------------ SDO server
    def on_sdo(self, data: bytes) -> None:
        if self._nmt in (NmtState.STOPPED, NmtState.BOOT_UP):
            return  # CiA 301: no SDO in STOPPED
        if len(data) < 8:
            return
        self._sdo.on_request(c301.SDO_RX + self.node_id, data, 0.0)
        self._emit_event_tpdos()

    def _var(self, index: int, subindex: int) -> objectdictionary.ODVariable:
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

    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        """canopen SdoServer hook: upload."""
        var = self._var(index, subindex)
        if check_readable and not var.readable:
            raise SdoAbortedError(ABORT_READ_WRITEONLY)
        value = self._values[(var.index, var.subindex)]
        return var.encode_raw(value)

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        """canopen SdoServer hook: download, with the checks a real drive makes."""
        var = self._var(index, subindex)
        if check_writable and not var.writable:
            raise SdoAbortedError(ABORT_WRITE_READONLY)
        if var.data_type in objectdictionary.NUMBER_TYPES and 8 * len(data) != len(var):
            raise SdoAbortedError(ABORT_LENGTH_NOT_MATCHED)
        value = var.decode_raw(bytes(data))
        key = (var.index, var.subindex)
        self._check_write(key, value)
        self._values[key] = value
        self._after_write(key, value)

    def _check_write(self, key: Key, value: Any) -> None:
        index, sub = key
        if key == MODE and not self._mode_supported(value):
            raise SdoAbortedError(ABORT_INVALID_VALUE)
        if index in SCALING and value == 0 and (index == c.RATED_TORQUE or sub > 0):
            raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
        if key == (c301.PREDEFINED_ERROR_FIELD, 0) and value != 0:
            raise SdoAbortedError(ABORT_INVALID_VALUE)
        if 0x1400 <= index <= 0x1403 or 0x1800 <= index <= 0x1803:
            if sub == 1:
                current = self._values[key]
                if not current & PDO_NOT_VALID and not value & PDO_NOT_VALID \
                        and (current ^ value) & 0x7FF:
                    raise SdoAbortedError(ABORT_INVALID_VALUE)  # CiA 301: invalidate first
                if value & 0x3FFFF800:  # 11-bit identifiers only
                    raise SdoAbortedError(ABORT_INVALID_VALUE)
            return
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            comm = index - 0x200
            if not self._values[(comm, 1)] & PDO_NOT_VALID:
                raise SdoAbortedError(ABORT_APPLICATION_DEVICE_STATE)  # mapping of a valid PDO
            if sub == 0:
                self._check_mapping(index, value, tx=index >= 0x1A00)
            elif self._values[(index, 0)] != 0:
                raise SdoAbortedError(ABORT_APPLICATION_DEVICE_STATE)  # sub 0 must be 0 first

    def _check_mapping(self, map_index: int, count: int, tx: bool) -> None:
        if count > 8:
            raise SdoAbortedError(ABORT_INVALID_VALUE)
        bits = 0
        for sub in range(1, count + 1):
            entry = self._values[(map_index, sub)]
            index, subindex, length = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            var = self._var(index, subindex)
            if not var.pdo_mappable or var.data_type not in objectdictionary.NUMBER_TYPES \
                    or not isinstance(var.STRUCT_TYPES.get(var.data_type), struct.Struct) \
                    or not (var.readable if tx else var.writable) \
                    or length != len(var):
                raise SdoAbortedError(ABORT_PDO_CANNOT_MAP)
            bits += length
        if bits > 64:
            raise SdoAbortedError(ABORT_PDO_LENGTH_EXCEEDED)

    def _after_write(self, key: Key, value: Any) -> None:
        index = key[0]
        if key == CONTROLWORD:
            self._on_controlword(value)
        elif key == MODE:
            self._values[MODE_DISPLAY] = value
        elif index == c301.PRODUCER_HEARTBEAT_TIME:
            self._start_heartbeat()
        elif index == c301.CONSUMER_HEARTBEAT_TIME:
            self._load_consumers()
        elif index == c301.PREDEFINED_ERROR_FIELD:
            self._errors.clear()
        elif index in SCALING:
            self._update_scales()
        elif 0x1400 <= index <= 0x1A03:
            self._build_pdos()

    # ------------------------------------------------------------------ PDOs
    def _build_pdos(self) -> None:
        self._rpdos = [self._compile(0x1400 + n, 0x1600 + n, n) for n in range(4)]
        self._tpdos = [self._compile(0x1800 + n, 0x1A00 + n, n) for n in range(4)]
        self._event_tpdos = [p for p in self._tpdos if p.valid and p.trans_type >= 254]
        self._seg.set_rpdo_routes(self, {p.cob_id: p for p in self._rpdos if p.valid})

    def _compile(self, comm: int, mapping: int, number: int) -> _Pdo:
        raw = self._values[(comm, 1)]
        keys: list[Key] = []
        fmt = "<"
        for sub in range(1, self._values[(mapping, 0)] + 1):
            entry = self._values[(mapping, sub)]
            var = self._var(entry >> 16, (entry >> 8) & 0xFF)
            keys.append((var.index, var.subindex))
            assert var.data_type is not None  # mappable objects have one (_check_mapping)
            fmt += var.STRUCT_TYPES[var.data_type].format.lstrip("<")
        values_of: Callable[[dict[Key, Any]], tuple[Any, ...]]
        if keys:
            values_of = itemgetter(*keys)
            if len(keys) == 1:
                single = values_of
                values_of = lambda values: (single(values),)  # noqa: E731
        else:
            values_of = lambda values: ()  # noqa: E731
        return _Pdo(number=number, cob_id=raw & 0x7FF, valid=not raw & PDO_NOT_VALID,
                    trans_type=self._values[(comm, 2)], keys=tuple(keys),
                    layout=struct.Struct(fmt), values_of=values_of)

    def on_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        if self._nmt != NmtState.OPERATIONAL:
            return
        if len(data) < pdo.layout.size:
            self._emcy(c301.EMCY_PDO_LENGTH)
            return
        if pdo.trans_type <= 240:
            pdo.pending = bytes(data)  # synchronous: takes effect at the next SYNC
            return
        self._apply_rpdo(pdo, data)
        self._emit_event_tpdos()

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        for key, value in zip(pdo.keys, pdo.layout.unpack_from(data)):
            if key == MODE and not self._mode_supported(value):
                continue  # a real drive ignores an unsupported mode from a PDO
            self._values[key] = value
            if key == CONTROLWORD:
                self._on_controlword(value)
            elif key == MODE:
                self._values[MODE_DISPLAY] = value

    def _send_tpdo(self, pdo: _Pdo) -> None:
        data = pdo.layout.pack(*pdo.values_of(self._values))
        pdo.last = data
        if self._tpdo_delay > 0:
            self._seg.schedule(self._seg.clock() + self._tpdo_delay, self._tx, pdo.cob_id, data)
        else:
            self._tx(pdo.cob_id, data)

    def _emit_event_tpdos(self) -> None:
        if self._nmt != NmtState.OPERATIONAL or not self._event_tpdos:
            return
        for pdo in self._event_tpdos:
            if pdo.layout.pack(*pdo.values_of(self._values)) != pdo.last:
                self._send_tpdo(pdo)

    # ------------------------------------------------------------------ SYNC cycle
    def prepare_step(self, dt: float, on_sync: bool) -> None:
        """Apply synchronous RPDOs and write this joint's command into the dynamics."""
        if on_sync and self._answer_sync and self._nmt == NmtState.OPERATIONAL:
            for pdo in self._rpdos:
                if pdo.pending is not None:
                    data, pdo.pending = pdo.pending, None
                    self._apply_rpdo(pdo, data)
        dyn, j = self._dyn, self.joint
        limit = self._values[(c.MAX_TORQUE, 0)] * self._nm_per_permille
        dyn.torque_limit[j] = limit
        dyn.target_velocity[j] = 0.0
        dyn.torque_feedforward[j] = 0.0
        state = self._state
        if state not in POWERED or self._sto_low:
            dyn.mode[j] = LoopMode.OFF
            return
        halt = bool(self._values[CONTROLWORD] & c.CW_HALT)
        if state == State402.OPERATION_ENABLED and halt and not self._ramping:
            self._start_ramp(self._quick_stop_decel(), then=None)
        elif state == State402.OPERATION_ENABLED and not halt and self._ramping \
                and self._ramp_then is None:
            self._ramping = False  # halt released
        if self._ramping:
            v = self._ramp_velocity
            step = self._ramp_decel * dt
            self._ramp_velocity = math.copysign(max(abs(v) - step, 0.0), v)
            if self._ramp_velocity == 0.0:
                self._ramp_zero_time += dt
            dyn.mode[j] = LoopMode.VELOCITY
            dyn.target_velocity[j] = self._ramp_velocity
            return
        if state != State402.OPERATION_ENABLED:  # quick stop active after its ramp: hold
            dyn.mode[j] = LoopMode.VELOCITY
            return
        scale = self._inc_per_rad
        mode = self._values[MODE_DISPLAY]
        if mode == c.Mode.CSP:
            dyn.mode[j] = LoopMode.POSITION
            dyn.target_position[j] = self._values[(c.TARGET_POSITION, 0)] / scale
            dyn.target_velocity[j] = self._values[(c.VELOCITY_OFFSET, 0)] / scale
            dyn.torque_feedforward[j] = (self._values[(c.TORQUE_OFFSET, 0)]
                                         * self._nm_per_permille)
        elif mode == c.Mode.CSV:
            dyn.mode[j] = LoopMode.VELOCITY
            dyn.target_velocity[j] = (self._values[(c.TARGET_VELOCITY, 0)]
                                      + self._values[(c.VELOCITY_OFFSET, 0)]) / scale
            dyn.torque_feedforward[j] = (self._values[(c.TORQUE_OFFSET, 0)]
                                         * self._nm_per_permille)
        elif mode == c.Mode.CST:
            dyn.mode[j] = LoopMode.TORQUE
            dyn.torque_feedforward[j] = ((self._values[(c.TARGET_TORQUE, 0)]
                                          + self._values[(c.TORQUE_OFFSET, 0)])
                                         * self._nm_per_permille)
        else:
            dyn.mode[j] = LoopMode.OFF  # no cyclic mode selected: no torque

    def finish_step(self, on_sync: bool) -> None:
        """After the dynamics step: end ramps, sample actual values, send TPDOs."""
        if self._ramping and self._ramp_velocity == 0.0 and (
                abs(self._dyn.velocity[self.joint]) < STOPPED_VELOCITY
                or self._ramp_zero_time >= STANDSTILL_TIME):
            then = self._ramp_then
            if then is not None:
                self._ramping = False
                self._set_state(then)
        self._sample()
        if on_sync and self._answer_sync and self._nmt == NmtState.OPERATIONAL:
            for pdo in self._tpdos:
                if not pdo.valid or pdo.trans_type > 240:
                    continue
                if pdo.trans_type == 0:  # acyclic synchronous: on SYNC, when changed
                    if pdo.layout.pack(*pdo.values_of(self._values)) != pdo.last:
                        self._send_tpdo(pdo)
                    continue
                pdo.counter += 1
                if pdo.counter >= pdo.trans_type:
                    pdo.counter = 0
                    self._send_tpdo(pdo)
        self._emit_event_tpdos()

    def _sample(self) -> None:
        j, values = self.joint, self._values
        q = self._dyn.position[j] * self._inc_per_rad
        if self._position_noise:
            q += self._seg.rng.normal(0.0, self._position_noise)
        values[POSITION] = _wrap(q, 32)
        values[VELOCITY] = _clamp(self._dyn.velocity[j] * self._inc_per_rad, 32)
        values[TORQUE] = _clamp(self._dyn.torque[j] / self._nm_per_permille, 16)

    def _update_scales(self) -> None:
        v = self._values
        increments = v[(c.POSITION_ENCODER_RESOLUTION, 1)] / v[(c.POSITION_ENCODER_RESOLUTION, 2)]
        ratio = v[(c.GEAR_RATIO, 1)] / v[(c.GEAR_RATIO, 2)]
        self._inc_per_rad = increments * ratio / (2.0 * math.pi)
        # torque objects are motor torque; an ideal gearbox multiplies it by the ratio
        self._nm_per_permille = v[(c.RATED_TORQUE, 0)] / 1e6 * ratio

    # ------------------------------------------------------------------ CiA 402
    def _mode_supported(self, mode: int) -> bool:
        supported = self._values[(c.SUPPORTED_DRIVE_MODES, 0)]
        return mode == 0 or (0 < mode <= 32 and bool(supported >> (mode - 1) & 1))

    def _set_state(self, state: State402) -> None:
        self._state = state
        sw = c.STATUSWORD_OF_STATE[state] | c.SW_REMOTE
        if state != State402.QUICK_STOP_ACTIVE:
            sw |= c.SW_QUICK_STOP
        if state in VOLTAGE_STATES and not self._sto_low:
            sw |= c.SW_VOLTAGE_ENABLED
        if self._sto_low:
            sw |= c.SW_WARNING
        self._values[STATUSWORD] = sw ^ self._statusword_xor
        if state not in POWERED:
            self._ramping = False

    def _on_controlword(self, cw: int) -> None:
        rising_reset = bool(cw & 0x80) and not self._last_controlword & 0x80
        self._last_controlword = cw
        s = self._state
        S = State402
        if s == S.FAULT:
            if rising_reset:
                self._fault_reset()
            return
        if s in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE):
            return
        if not cw & 0x02:  # disable voltage: transitions 7, 9, 10, 12
            if s in VOLTAGE_STATES:
                self._set_state(S.SWITCH_ON_DISABLED)
            return
        if not cw & 0x04:  # quick stop: transitions 7, 10, 11
            if s in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON):
                self._set_state(S.SWITCH_ON_DISABLED)
            elif s == S.OPERATION_ENABLED:
                self._quick_stop()
            return
        if s == S.QUICK_STOP_ACTIVE:  # transition 16, only for options 5-8
            if cw & 0x0F == 0x0F and self._values[(c.QUICK_STOP_OPTION, 0)] in (5, 6, 7, 8):
                self._ramping = False
                self._set_state(S.OPERATION_ENABLED)
            return
        if not cw & 0x01:  # shutdown: transitions 2, 6, 8
            if s == S.SWITCH_ON_DISABLED:
                if not self._sto_low:
                    self._set_state(S.READY_TO_SWITCH_ON)
            elif s == S.SWITCHED_ON:
                self._set_state(S.READY_TO_SWITCH_ON)
            elif s == S.OPERATION_ENABLED:
                self._leave_operation(c.SHUTDOWN_OPTION, S.READY_TO_SWITCH_ON)
            return
        if s == S.READY_TO_SWITCH_ON:  # switch on (3), with enable operation also 4
            self._set_state(S.SWITCHED_ON)
            s = S.SWITCHED_ON
        if s == S.SWITCHED_ON and cw & 0x08:
            self._ramping = False
            self._set_state(S.OPERATION_ENABLED)
        elif s == S.OPERATION_ENABLED and not cw & 0x08:  # disable operation (5)
            self._leave_operation(c.DISABLE_OPERATION_OPTION, S.SWITCHED_ON)

    def _leave_operation(self, option_index: int, target: State402) -> None:
        """Shutdown / disable operation from operation enabled: option 1 ramps down first."""
        if self._values[(option_index, 0)] == 1 and not self._sto_low:
            self._start_ramp(self._quick_stop_decel(), then=target)
        else:
            self._set_state(target)

    def _quick_stop(self) -> None:
        option = self._values[(c.QUICK_STOP_OPTION, 0)]
        if option <= 0 or self._sto_low:  # disable drive function: coast
            self._set_state(State402.SWITCH_ON_DISABLED)
            return
        self._set_state(State402.QUICK_STOP_ACTIVE)
        # 1/5 slow-down ramp, 2/6 quick-stop ramp (both 0x6085 here), 3/4/7/8 current limit
        decel = self._quick_stop_decel() if option in (1, 2, 5, 6) else math.inf
        then = State402.SWITCH_ON_DISABLED if option <= 4 else None
        self._start_ramp(decel, then)

    def _quick_stop_decel(self) -> float:
        return float(max(self._values[(c.QUICK_STOP_DECELERATION, 0)], 1)) / self._inc_per_rad

    def _start_ramp(self, decel: float, then: State402 | None) -> None:
        self._ramping = True
        self._ramp_velocity = float(self._dyn.velocity[self.joint])
        self._ramp_decel = decel
        self._ramp_then = then
        self._ramp_zero_time = 0.0

    def _fault(self, code: int) -> None:
        """Transition 13 (fault reaction: quick-stop ramp if powered), then 14."""
        self._error_register |= 1 | ERROR_REGISTER_BIT.get(code >> 12, 0)
        self._values[ERROR_CODE] = code
        self._record_error(code)
        self._emcy(code)
        if self._state == State402.FAULT:
            return
        powered = self._state in POWERED and not self._sto_low
        self._set_state(State402.FAULT_REACTION_ACTIVE)
        if powered:
            self._start_ramp(self._quick_stop_decel(), then=State402.FAULT)
        else:
            self._set_state(State402.FAULT)

    def _fault_reset(self) -> None:
        """Transition 15 on the rising edge of controlword bit 7: EMCY 0x0000."""
        self._error_register = 0
        self._hb_lost.clear()
        self._values[ERROR_CODE] = 0
        self._set_state(State402.SWITCH_ON_DISABLED)
        if self._sto_low:
            self._error_register |= 1
        self._emcy(c301.EMCY_NO_ERROR)

    def _set_sto(self, low: bool) -> None:
        if low == self._sto_low:
            return
        self._sto_low = low
        if low:
            self._error_register |= 1
            if self._state in VOLTAGE_STATES:
                self._set_state(State402.SWITCH_ON_DISABLED)
            else:
                self._set_state(self._state)  # warning bit
            self._emcy(c301.EMCY_STO)
        else:
            self._set_state(self._state)
            if not self._errors_active():
                self._error_register = 0
                self._emcy(c301.EMCY_NO_ERROR)

    def _errors_active(self) -> bool:
        return (self._state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)
                or self._sto_low or bool(self._hb_lost))

    # ------------------------------------------------------------------ EMCY and TX
    def _record_error(self, code: int) -> None:
        self._errors.insert(0, code)
        del self._errors[8:]
        for sub in range(1, 9):
            key = (c301.PREDEFINED_ERROR_FIELD, sub)
            if key in self._values:
                self._values[key] = self._errors[sub - 1] if sub <= len(self._errors) else 0
        self._values[(c301.PREDEFINED_ERROR_FIELD, 0)] = len(self._errors)

    def _emcy(self, code: int) -> None:
        self._values[ERROR_REGISTER] = self._error_register
        if self._nmt == NmtState.STOPPED:
            return  # CiA 301: no EMCY in STOPPED
        self._tx(c301.EMCY + self.node_id,
                 struct.pack("<HB5s", code, self._error_register, bytes(5)))

    def _tx(self, cob_id: int, data: bytes) -> None:
        if not self._silent:
            self._seg.send(cob_id, data)

    def _babble_burst(self, cob_id: int, data: bytes, burst: int) -> None:
        n = min(burst, self._babble_left)
        for _ in range(n):
            self._seg.send(cob_id, data)
        self._babble_left -= n
        if self._babble_left > 0:
            self._seg.schedule(self._seg.clock() + 0.001, self._babble_burst, cob_id, data,
                               burst)


def load_object_dictionary(eds_path: str, node_id: int) -> objectdictionary.ObjectDictionary:
    """Import an EDS for one node ($NODEID resolved), with a clear error for a bad path."""
    try:
        return canopen.import_od(str(eds_path), node_id)
    except FileNotFoundError:
        raise FileNotFoundError(f"simulated drive {node_id}: EDS file {eds_path} not found") \
            from None
