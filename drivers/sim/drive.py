"""One simulated CiA 402 servo drive (one CANopen node, one or more axes), as seen from
the CAN bus.

It behaves like a real drive where a master can tell the difference: boot-up and NMT,
heartbeat producer and consumer, node guarding, the 0x6007 reaction, an SDO server on the
EDS (PDO mapping and communication objects written by SDO take effect, with the CiA 301 rules for
changing them), synchronous and event-driven TPDOs, RPDOs only in OPERATIONAL, the complete
CiA 402 state machine with quick stop, fault reaction and fault reset, CSP/CSV/CST, EMCY,
and an STO input. Faults can be injected to test a master's supervision.

The drive is composed of one object per CANopen service, as canopen's LocalNode is:
``objects`` (object dictionary and SDO server, objects.py), ``nmt`` (NMT state and
heartbeats, nmt.py), ``pdos`` (pdo.py), ``cia402`` (state machine and loops,
state_machine.py) and ``emcy`` (error register, history, EMCY, faults.py). This module wires
them: what a write, an NMT command or a lost heartbeat does to the other services is here.

A node may have up to eight axes (CiA 402-2, e.g. a dual-channel controller): one CANopen
node (one NMT state, heartbeat, SDO server, PDO set, EMCY producer and error register) with
one SimulatedAxis per axis (axis.py): its objects at +0x800 per axis (objects.AxisKeys), its factor
group, its CiA 402 state machine and its own joint (consecutive joints, axis 1 first). A
lost connection makes every axis react with its own 0x6007; a fault of one axis is the
node's EMCY with the axis's 0x603F. The node's read-only properties and fault injection are
axis 1's; ``axes`` gives every axis's.

A drive never owns a thread or a socket: its segment feeds it frames and timer events with
the segment lock held, and sends what it transmits (port.Segment).
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from typing import Any

import can
from canopen import objectdictionary

from ..files.identity import Identity
from ..protocol import cia301 as c301
from ..protocol import cia402 as c
from ..protocol.cia301 import NmtCommand, NmtState, ObjectKey
from ..protocol.cia402 import State402
from .axis import SimulatedAxis
from .faults import Babble, EmcyProducer, InjectedFaults, register_bits
from .limits import OBJECTS as LIMIT_OBJECTS
from .nmt import NmtSlave
from .objects import (
    SCALING,
    AxisKeys,
    ObjectDictionaryServer,
    axes_problem,
    axis_of,
    fallback_values,
    for_axes,
    load_object_dictionary,
)
from .pdo import PdoService
from .port import Segment

__all__ = ["SimulatedDrive", "load_object_dictionary"]


_OPERATIONAL = NmtState.OPERATIONAL  # a module global: an enum member's look-up costs more


class SimulatedDrive:
    """A CiA 402 servo drive on a SimulatedSegment; use ``segment.drives[node_id]``.

    ``axes`` (1..8) CiA 402 axes in the one node, on joints ``joint``, ``joint + 1``, ...
    The node's properties and fault injection are axis 1's unless they are the node's
    (NMT, error register, STO, the injected communication faults); ``axes[n - 1]`` or
    ``axis(n)`` is axis n. Properties are safe to read from any thread; the
    fault-injection methods take the segment lock.
    """

    def __init__(self, segment: Segment, node_id: int, joint: int,
                 object_dictionary: objectdictionary.ObjectDictionary,
                 fallbacks: Mapping[ObjectKey, Any] | None = None, axes: int = 1) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CANopen node id must be 1..127, got {node_id}")
        problem = axes_problem(object_dictionary, axes)
        if problem:
            raise ValueError(f"simulated drive {node_id}: {problem}")
        self.node_id = node_id
        self.joint = joint
        self.object_dictionary = object_dictionary
        self._seg = segment
        self._dyn = segment.dynamics
        self._faults = InjectedFaults()
        self._babble = Babble(segment)
        self.objects = ObjectDictionaryServer(
            object_dictionary, node_id, self._tx, self._after_write,
            for_axes(fallback_values(1 << 20, 1.0) if fallbacks is None else fallbacks, axes),
            [AxisKeys.of(n) for n in range(1, axes + 1)], pdo_bytes=64 if segment.fd else 8)
        self._values = self.objects.values
        self.nmt = NmtSlave(node_id, segment, self._values, self._tx,
                            on_lost=self._heartbeat_lost, on_regained=self._errors_cleared)
        self.emcy = EmcyProducer(node_id, self._values, self._tx,
                                 stopped=lambda: self.nmt.state == NmtState.STOPPED)
        self._sto_low = False
        self.axes = tuple(SimulatedAxis(self, n, joint + n - 1, dynamics=self._dyn,
                                        faults=self._faults, rng=segment.rng,
                                        on_fault_reset=self._fault_reset)
                          for n in range(1, axes + 1))
        self.cia402 = self.axes[0].cia402
        # each SYNC, per axis (bound once: this runs for every drive at 1 kHz)
        self._command_joints = tuple(axis.cia402.command_joint for axis in self.axes)
        self._after_steps = tuple((axis.cia402.end_ramp, axis.sample) for axis in self.axes)
        self.pdos = PdoService(node_id, segment, self.objects, self.nmt, self.emcy,
                               self._faults, self._tx, self._tx_frame,
                               [(axis.keys, axis.cia402.on_controlword) for axis in self.axes])

    def axis(self, number: int) -> SimulatedAxis:
        """Axis ``number`` (1 = the first)."""
        if not 1 <= number <= len(self.axes):
            raise ValueError(f"simulated drive {self.node_id} has axes 1..{len(self.axes)}, "
                             f"not {number}")
        return self.axes[number - 1]

    # ------------------------------------------------------------------ read-only view
    @property
    def nmt_state(self) -> NmtState:
        return self.nmt.state

    @property
    def state402(self) -> State402:
        return self.axes[0].state402

    @property
    def statusword(self) -> int:
        return self.axes[0].statusword

    @property
    def controlword(self) -> int:
        return self.axes[0].controlword

    @property
    def mode_display(self) -> int:
        return self.axes[0].mode_display

    @property
    def error_code(self) -> int:
        return self.axes[0].error_code

    @property
    def error_register(self) -> int:
        return self.emcy.register

    @property
    def position_increments(self) -> int:
        return self.axes[0].position_increments

    @property
    def velocity_increments(self) -> int:
        return self.axes[0].velocity_increments

    @property
    def torque_per_mille(self) -> int:
        return self.axes[0].torque_per_mille

    @property
    def position_rad(self) -> float:
        """True joint position (no sensor noise)."""
        return self.axes[0].position_rad

    @property
    def velocity_rad_s(self) -> float:
        return self.axes[0].velocity_rad_s

    @property
    def torque_nm(self) -> float:
        """Joint torque the power stage applied in the last step."""
        return self.axes[0].torque_nm

    @property
    def increments_per_rad(self) -> float:
        """Joint radians to position increments (0x608F and 0x6091)."""
        return self.axes[0].increments_per_rad

    @property
    def nm_per_permille(self) -> float:
        """Joint torque of one per mille of rated torque (0x6076, gear ratio)."""
        return self.axes[0].nm_per_permille

    @property
    def sto_low(self) -> bool:
        return self._sto_low

    def od_value(self, index: int, subindex: int = 0) -> Any:
        """Current value of an object, as the SDO server would return it."""
        return self._values[(index, subindex)]

    def status_line(self) -> str:
        """Axis 1's status line (``status_lines``: every axis's)."""
        return self.axes[0].status_line()

    def status_lines(self) -> list[str]:
        return [axis.status_line() for axis in self.axes]

    # ------------------------------------------------------------------ fault injection
    @contextlib.contextmanager
    def _injecting(self) -> Iterator[None]:
        """The segment's lock for a change from outside (a test, the sim CLI), after the
        step of a SYNC whose RPDOs the drive already applied (one that waits for the
        group's joined step): the change comes after that SYNC, whole."""
        with self._seg.lock:
            self._seg.finish_pending_step()
            yield

    def trip_fault(self, code: int = c301.EMCY_GENERIC, axis: int = 1) -> None:
        """An internal fault of ``axis``: EMCY with ``code``, fault reaction, then FAULT."""
        if not 0 < code <= 0xFFFF:
            raise ValueError(f"EMCY error code must be 0x0001..0xFFFF, got 0x{code:X}")
        machine = self.axis(axis).cia402
        with self._injecting():
            machine.fault(code)
            self.pdos.emit_event_tpdos()

    def swap(self, identity: Identity) -> None:
        """Another drive in this one's place, as when a drive is swapped while the robot
        runs: it answers ``identity`` (the fields given; 0x1018) and powers on (boot-up,
        pre-operational, every object at its default)."""
        with self._injecting():
            for values in (self.objects.defaults, self.objects.values):
                values.update(identity.objects())
            self.power_on()

    def garble_statusword(self, xor: int = 0x0008) -> None:
        """Every statusword this drive reports (TPDO, SDO; every axis's) is XORed with
        ``xor`` from now on (0 = healthy again): a bit error in firmware. The default flips
        the fault bit, which makes switch on disabled, ready to switch on and switched on
        read as no CiA 402 state, and operation enabled as fault reaction active."""
        with self._injecting():
            for axis in self.axes:
                self._values[axis.keys.statusword] ^= self._faults.statusword_xor ^ xor
            self._faults.statusword_xor = xor

    def set_silent(self, silent: bool = True) -> None:
        """Transmit nothing at all (heartbeat, TPDO, EMCY, SDO), like a dead TX line.
        The drive keeps receiving and keeps following its targets."""
        with self._injecting():
            self._faults.silent = bool(silent)

    def set_sync_response(self, answer: bool) -> None:
        """False: ignore SYNC (no synchronous TPDOs, synchronous RPDOs not applied)."""
        with self._injecting():
            self._faults.answer_sync = bool(answer)

    def set_tpdo_delay(self, seconds: float) -> None:
        """Send every TPDO this late (0 = at once)."""
        if not 0 <= seconds <= 10:
            raise ValueError(f"TPDO delay must be 0..10 s, got {seconds}")
        with self._injecting():
            self._faults.tpdo_delay = float(seconds)

    def set_sto(self, low: bool) -> None:
        """The node's STO input low: the power stage of every axis is off and each holds in
        switch on disabled (EMCY EMCY_STO, warning bit); back high: EMCY 0x0000, the axes
        may be enabled."""
        low = bool(low)
        with self._injecting():
            if low == self._sto_low:
                return
            self._sto_low = low
            for axis in self.axes:
                axis.cia402.set_sto(low)
            if low:
                self.emcy.register |= 1
                self.emcy.emit(c301.EMCY_STO)
            else:
                self._errors_cleared()
            self.pdos.emit_event_tpdos()

    def set_position_noise(self, std_increments: float) -> None:
        """Gaussian noise (standard deviation, increments) on every axis's reported 0x6064."""
        if std_increments < 0:
            raise ValueError(f"noise must be >= 0, got {std_increments}")
        with self._injecting():
            self._faults.position_noise = float(std_increments)

    def babble(self, count: int = 1000, cob_id: int = 0x001, data: bytes = bytes(8),
               burst: int = 50) -> None:
        """Flood the bus with ``count`` frames of ``cob_id`` (a babbling node), ``burst``
        frames per millisecond, from the segment's timer thread. Bounded: at most 100000."""
        if not 1 <= count <= 100_000 or not 0 <= cob_id <= 0x7FF or len(data) > 8 or burst < 1:
            raise ValueError(f"babble: count 1..100000, cob_id 0..0x7FF, data <= 8 bytes, "
                             f"burst >= 1; got {count}, 0x{cob_id:X}, {len(data)}, {burst}")
        with self._injecting():
            self._babble.start(count, cob_id, data, burst)

    # ------------------------------------------------------------------ errors of the node
    def _fault_reset(self) -> None:
        """An axis's fault reset: the error register keeps what is still wrong (another
        axis's fault, STO), a lost heartbeat is forgotten; EMCY 0x0000."""
        register = 1 if self._sto_low else 0
        for axis in self.axes:
            if axis.cia402.faulted:
                register |= register_bits(axis.error_code)
        self.emcy.register = register
        self.nmt.lost.clear()
        self.emcy.emit(c301.EMCY_NO_ERROR)

    def _errors_cleared(self) -> None:
        """A condition went away (STO high, a heartbeat back): EMCY 0x0000 if nothing else
        is wrong now."""
        if not (self._sto_low or self.nmt.lost
                or any(axis.cia402.faulted for axis in self.axes)):
            self.emcy.register = 0
            self.emcy.emit(c301.EMCY_NO_ERROR)

    # ------------------------------------------------------------------ power-up and NMT
    def power_on(self) -> None:
        """Power-on / reset node: whole OD to defaults, every axis's CiA 402 state machine
        restarts."""
        self.objects.reset_all()
        self.emcy.clear_history()
        self.emcy.register = 1 if self._sto_low else 0
        dyn = self._dyn
        position, velocity, torque = (dyn.position.tolist(), dyn.velocity.tolist(),
                                      dyn.torque.tolist())
        for axis in self.axes:
            axis.update_units()
            axis.cia402.power_on()
            axis.sample(position, velocity, torque)
        self._reset_communication()

    def _reset_communication(self) -> None:
        """Communication objects to defaults, then boot-up and PRE-OPERATIONAL."""
        self.objects.reset_communication()
        self.nmt.boot_up()
        self.pdos.build()
        self.nmt.load_consumers()
        self.nmt.start_heartbeat()

    def _abort_connection(self) -> None:
        """Every axis's 0x6007 reaction."""
        for axis in self.axes:
            axis.cia402.abort_connection(c301.EMCY_HEARTBEAT)

    def on_nmt(self, command: int) -> None:
        if command == NmtCommand.START:
            self.pdos.build()
            self.nmt.state = NmtState.OPERATIONAL
        elif command == NmtCommand.STOP:
            self.nmt.state = NmtState.STOPPED
            self._abort_connection()
        elif command == NmtCommand.PRE_OPERATIONAL:
            self.nmt.state = NmtState.PRE_OPERATIONAL
        elif command == NmtCommand.RESET_NODE:
            self.power_on()
        elif command == NmtCommand.RESET_COMMUNICATION:
            self._abort_connection()
            self._reset_communication()
        self.pdos.emit_event_tpdos()

    def on_heartbeat(self, node: int, arrived: float) -> None:
        self.nmt.on_heartbeat(node, arrived)

    def on_guard_request(self, arrived: float) -> None:
        self.nmt.on_guard_request(arrived)  # a silent drive hears it, its answer is lost

    def _heartbeat_lost(self) -> None:
        """The manager's heartbeat or its guarding is lost: EMCY (once, from the node, unless
        an axis faults on it and sends its own), 0x1029 error behaviour, each axis's 0x6007
        reaction."""
        if all(self._values[axis.keys.abort_connection_option]
               != c.AbortConnectionOption.FAULT for axis in self.axes):
            self.emcy.flag(c301.EMCY_HEARTBEAT)
            self.emcy.record(c301.EMCY_HEARTBEAT)
            self.emcy.emit(c301.EMCY_HEARTBEAT)
        self.nmt.apply_error_behaviour()
        self._abort_connection()
        self.pdos.emit_event_tpdos()

    # ------------------------------------------------------------------ SDO
    def on_sdo(self, data: bytes) -> None:
        if self.nmt.state in (NmtState.STOPPED, NmtState.BOOT_UP):
            return  # CiA 301: no SDO in STOPPED
        if len(data) < 8:
            return
        self.objects.request(data)
        self.pdos.emit_event_tpdos()

    def _after_write(self, key: ObjectKey, value: Any) -> None:
        """An SDO download was accepted: make it take effect (on its axis's objects)."""
        index, subindex = key
        number, base = axis_of(index, len(self.axes))
        if number:
            axis = self.axes[number - 1]
            if key == axis.keys.controlword:
                axis.cia402.on_controlword(value)
            elif key == axis.keys.mode:
                self._values[axis.keys.mode_display] = value
            elif base in SCALING or base in LIMIT_OBJECTS:
                axis.update_units()
        elif index == c301.PRODUCER_HEARTBEAT_TIME:
            self.nmt.start_heartbeat()
        elif index == c301.CONSUMER_HEARTBEAT_TIME:
            self.nmt.load_consumers()
        elif index == c301.PREDEFINED_ERROR_FIELD:
            self.emcy.clear_history()
        elif 0x1400 <= index <= 0x1A03:
            self.pdos.rebuild(index)

    # ------------------------------------------------------------------ SYNC cycle
    def _answers_sync(self, on_sync: bool) -> bool:
        return on_sync and self._faults.answer_sync and self.nmt.state == _OPERATIONAL

    def prepare_step(self, dt: float, on_sync: bool) -> None:
        """Apply synchronous RPDOs and write each axis's command into the dynamics."""
        if self._answers_sync(on_sync):
            self.pdos.apply_synchronous()
        for command_joint in self._command_joints:
            command_joint(dt)

    def finish_step(self, on_sync: bool, position: list[float], velocity: list[float],
                    torque: list[float]) -> None:
        """After the dynamics step: end ramps, sample actual values, send TPDOs. The joint
        values come as the segment's lists of Python floats (one ``tolist`` per array and
        step instead of a numpy scalar per drive and value: this runs at 1 kHz)."""
        for end_ramp, sample in self._after_steps:
            end_ramp()
            sample(position, velocity, torque)
        if self._answers_sync(on_sync):
            self.pdos.send_synchronous()
        self.pdos.emit_event_tpdos()

    def _tx(self, cob_id: int, data: bytes) -> None:
        if not self._faults.silent:
            self._seg.send(cob_id, data)

    def _tx_frame(self, msg: can.Message) -> None:
        if not self._faults.silent:
            self._seg.send_frame(msg)
