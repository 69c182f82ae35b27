"""The simulated drive's CiA 402 side: the state machine, its ramps and the drive's loops.

The state machine follows the controlword (transitions 2-16, with the shutdown, disable
operation and quick stop option codes), the fault reaction (transition 13: a quick-stop ramp
when powered, then FAULT), fault reset on the rising edge of controlword bit 7, the STO input
and the 0x6007 reaction to a lost connection. Each SYNC, ``command_joint`` turns the state,
the mode (CSP/CSV/CST) and the targets into this joint's loop command in the segment's
dynamics; ``end_ramp`` ends a ramp once the joint stands still.

One StateMachine402 per axis: it reads and writes its axis's objects in the node's values
through the axis's ``AxisKeys`` (objects.py), so axis 2 runs the same code on 0x6840 and
its siblings. The node's error register and EMCY (faults.py) are shared: a fault reset or
the STO input ends in the node's reaction (drive.py), which knows the other axes.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from ..protocol import cia301
from ..protocol import cia402 as c
from ..protocol.cia301 import ObjectKey
from ..protocol.cia402 import State402
from .dynamics import JointDynamics, LoopMode
from .faults import EmcyProducer, InjectedFaults
from .limits import AxisLimits
from .objects import AxisKeys

# States in which the power stage is on (the loops may produce torque).
POWERED = (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE,
           State402.FAULT_REACTION_ACTIVE)
FAULTY = (State402.FAULT_REACTION_ACTIVE, State402.FAULT)
# States left for switch on disabled when STO goes low or on "disable voltage".
VOLTAGE_STATES = (State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON,
                  State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE)
# A ramp has ended once its command is zero and the joint is slower than this, or after
# its command has been zero this long (standstill window and time of a real drive).
STOPPED_VELOCITY = 0.01  # rad/s
STANDSTILL_TIME = 0.05  # s
CW_BIT4 = 1 << 4        # IP: enable interpolation; PP: new set-point
CW_RELATIVE = 1 << 6    # PP: the set-point is relative to the last one
SW_BIT12 = 1 << 12      # IP: interpolation active; PP: set-point acknowledge
PP_WINDOW_INCREMENTS = 100  # PP: target reached within this many increments
SW_HOMING_ERROR = 1 << 13
HOMING_TIME = 0.2  # s a simulated homing takes


# What command_joint reads each SYNC, as plain ints and pre-built keys (AxisKeys): an enum
# member or a key tuple built per access costs more than the read, and this runs for every
# axis at 1 kHz.
_LOOP_OFF, _LOOP_TORQUE, _LOOP_VELOCITY, _LOOP_POSITION = (
    int(LoopMode.OFF), int(LoopMode.TORQUE), int(LoopMode.VELOCITY), int(LoopMode.POSITION))
_IP, _PP, _HOMING, _PV, _CSP, _CSV, _CST = (
    int(c.Mode.INTERPOLATED_POSITION), int(c.Mode.PROFILE_POSITION), int(c.Mode.HOMING),
    int(c.Mode.PROFILE_VELOCITY), int(c.Mode.CSP), int(c.Mode.CSV), int(c.Mode.CST))
_ENABLED = State402.OPERATION_ENABLED
_CW_HALT = c.CW_HALT


class FactorGroup:
    """Joint units from an axis's factor group: 0x608F encoder resolution, 0x6091 gear
    ratio, 0x6076 rated torque (torque objects are motor torque; an ideal gearbox multiplies
    it by the ratio)."""

    def __init__(self, keys: AxisKeys) -> None:
        self._keys = keys
        self.increments_per_rad = 1.0
        self.motor_revs_per_rad = 1.0 / (2.0 * math.pi)
        self.nm_per_permille = 1.0

    def update(self, v: dict[ObjectKey, Any]) -> None:
        # a factor of 0 (a file's stated default; SDO writes of 0 are refused) counts as 1
        k = self._keys
        increments = (v[k.resolution_increments] or 1) / (v[k.resolution_revolutions] or 1)
        ratio = (v[k.gear_motor] or 1) / (v[k.gear_shaft] or 1)
        self.increments_per_rad = increments * ratio / (2.0 * math.pi)
        self.motor_revs_per_rad = ratio / (2.0 * math.pi)
        self.nm_per_permille = (v[k.rated_torque] or 1000) / 1e6 * ratio


class StateMachine402:
    """One axis's CiA 402 state machine on its objects (``keys``) and its joint.

    ``on_fault_reset`` is the node's part of a fault reset (transition 15): its error
    register and the EMCY that says the error is gone. ``limits``: the axis's own
    (0x607D, 0x607F/0x6080, 0x6065/0x6066: limits.py), applied to its loop commands.
    """

    def __init__(self, joint: int, dynamics: JointDynamics, values: dict[ObjectKey, Any],
                 scaling: FactorGroup, emcy: EmcyProducer, faults: InjectedFaults,
                 keys: AxisKeys, on_fault_reset: Callable[[], None]) -> None:
        self._j = joint
        self._dyn = dynamics
        self._values = values
        self._scale = scaling
        self._emcy = emcy
        self._faults = faults
        self._keys = keys
        self._on_fault_reset = on_fault_reset
        self.limits = AxisLimits(keys, values)
        self.following_error = False  # statusword bit 13 until a fault reset
        self.state = State402.NOT_READY_TO_SWITCH_ON
        self.sto_low = False
        self._last_controlword = 0
        # ramps (quick stop, halt, fault reaction, shutdown/disable operation option 1)
        self._ramping = False
        self._ramp_velocity = 0.0
        self._ramp_decel = 0.0
        self._ramp_then: State402 | None = None
        self._ramp_zero_time = 0.0
        # mode-specific statusword bits (12: PP set-point acknowledge / IP active, 10:
        # target reached) and PP's latched set-point
        self._mode_bits = 0
        self._new_setpoint = False  # controlword bit 4 at the last SYNC
        self._pp_target: float | None = None  # rad
        # homing: time left of a running homing (None: none running), and the offset that
        # homing puts between the joint and its reported position (increments)
        self._homing_left: float | None = None
        self.position_offset = 0.0

    def power_on(self) -> None:
        """NOT READY TO SWITCH ON, then transition 1 (automatic) to SWITCH ON DISABLED."""
        self._last_controlword = 0
        self._ramping = False
        self.following_error = False
        self.position_offset = 0.0  # an incremental encoder forgets its home at power-on
        self.state = State402.NOT_READY_TO_SWITCH_ON
        self.set_state(State402.SWITCH_ON_DISABLED)

    def set_state(self, state: State402) -> None:
        self.state = state
        if state != State402.OPERATION_ENABLED:
            self._mode_bits = 0
            self._pp_target = None
            self._new_setpoint = False
            self._homing_left = None
        sw = c.STATUSWORD_OF_STATE[state] | c.SW_REMOTE | self._mode_bits
        if self.following_error:
            sw |= c.SW_FOLLOWING_ERROR
        if state != State402.QUICK_STOP_ACTIVE:
            sw |= c.SW_QUICK_STOP
        if state in VOLTAGE_STATES and not self.sto_low:
            sw |= c.SW_VOLTAGE_ENABLED
        if self.sto_low:
            sw |= c.SW_WARNING
        self._values[self._keys.statusword] = sw ^ self._faults.statusword_xor
        if state not in POWERED:
            self._ramping = False

    # ------------------------------------------------------------------ controlword
    def on_controlword(self, cw: int) -> None:
        rising_reset = bool(cw & 0x80) and not self._last_controlword & 0x80
        self._last_controlword = cw
        s = self.state
        S = State402
        if s == S.FAULT:
            if rising_reset:
                self._fault_reset()
            return
        if s in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE):
            return
        if not cw & 0x02:  # disable voltage: transitions 7, 9, 10, 12
            if s in VOLTAGE_STATES:
                self.set_state(S.SWITCH_ON_DISABLED)
            return
        if not cw & 0x04:  # quick stop: transitions 7, 10, 11
            self._on_quick_stop_command(s)
            return
        if s == S.QUICK_STOP_ACTIVE:  # transition 16, only for options 5-8
            if cw & 0x0F == 0x0F and self._values[self._keys.quick_stop_option] in (5, 6, 7, 8):
                self._ramping = False
                self.set_state(S.OPERATION_ENABLED)
            return
        if not cw & 0x01:  # shutdown: transitions 2, 6, 8
            self._on_shutdown(s)
            return
        if s == S.READY_TO_SWITCH_ON:  # switch on (3), with enable operation also 4
            self.set_state(S.SWITCHED_ON)
            s = S.SWITCHED_ON
        if s == S.SWITCHED_ON and cw & 0x08:
            self._ramping = False
            self.set_state(S.OPERATION_ENABLED)
        elif s == S.OPERATION_ENABLED and not cw & 0x08:  # disable operation (5)
            self._leave_operation(self._keys.disable_operation_option, S.SWITCHED_ON)

    def _on_quick_stop_command(self, s: State402) -> None:
        """Controlword "quick stop" (bit 2 low): transitions 7, 10, 11."""
        if s in (State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON):
            self.set_state(State402.SWITCH_ON_DISABLED)
        elif s == State402.OPERATION_ENABLED:
            self._quick_stop()

    def _on_shutdown(self, s: State402) -> None:
        """Controlword "shutdown" (bit 0 low): transitions 2, 6, 8; STO low refuses 2."""
        if s == State402.SWITCH_ON_DISABLED:
            if not self.sto_low:
                self.set_state(State402.READY_TO_SWITCH_ON)
        elif s == State402.SWITCHED_ON:
            self.set_state(State402.READY_TO_SWITCH_ON)
        elif s == State402.OPERATION_ENABLED:
            self._leave_operation(self._keys.shutdown_option, State402.READY_TO_SWITCH_ON)

    def _leave_operation(self, option: ObjectKey, target: State402) -> None:
        """Shutdown / disable operation from operation enabled: option 1 ramps down first."""
        if self._values[option] == 1 and not self.sto_low:
            self._start_ramp(self._quick_stop_decel(), then=target)
        else:
            self.set_state(target)

    def _quick_stop(self) -> None:
        option = self._values[self._keys.quick_stop_option]
        if option <= 0 or self.sto_low:  # disable drive function: coast
            self.set_state(State402.SWITCH_ON_DISABLED)
            return
        self.set_state(State402.QUICK_STOP_ACTIVE)
        # 1/5 slow-down ramp, 2/6 quick-stop ramp (both 0x6085 here), 3/4/7/8 current limit
        decel = self._quick_stop_decel() if option in (1, 2, 5, 6) else math.inf
        then = State402.SWITCH_ON_DISABLED if option <= 4 else None
        self._start_ramp(decel, then)

    def _quick_stop_decel(self) -> float:
        value = self._values[self._keys.quick_stop_deceleration]
        if value <= 0:  # a file's placeholder 0: ten joint turns per second squared
            return 20.0 * math.pi
        return float(value) / self._scale.increments_per_rad

    def _start_ramp(self, decel: float, then: State402 | None) -> None:
        self._ramping = True
        self._ramp_velocity = float(self._dyn.velocity[self._j])
        self._ramp_decel = decel
        self._ramp_then = then
        self._ramp_zero_time = 0.0

    # ------------------------------------------------------------------ faults and inputs
    def abort_connection(self, code: int) -> None:
        """0x6007 reaction to heartbeat loss, NMT stop or reset communication."""
        option = self._values[self._keys.abort_connection_option]
        if option == c.AbortConnectionOption.FAULT:
            if self.state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                self.fault(code)
        elif option == c.AbortConnectionOption.DISABLE_VOLTAGE:
            if self.state in VOLTAGE_STATES:
                self.set_state(State402.SWITCH_ON_DISABLED)
        elif option == c.AbortConnectionOption.QUICK_STOP:
            if self.state == State402.OPERATION_ENABLED:
                self._quick_stop()
            elif self.state in (State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON):
                self.set_state(State402.SWITCH_ON_DISABLED)

    def fault(self, code: int) -> None:
        """Transition 13 (fault reaction: quick-stop ramp if powered), then 14."""
        self._emcy.flag(code)
        self._values[self._keys.error_code] = code
        self._emcy.record(code)
        self._emcy.emit(code)
        if self.state == State402.FAULT:
            return
        powered = self.state in POWERED and not self.sto_low
        self.set_state(State402.FAULT_REACTION_ACTIVE)
        if powered:
            self._start_ramp(self._quick_stop_decel(), then=State402.FAULT)
        else:
            self.set_state(State402.FAULT)

    @property
    def faulted(self) -> bool:
        return self.state in FAULTY

    def _fault_reset(self) -> None:
        """Transition 15 on the rising edge of controlword bit 7; then the node's reaction
        (EMCY 0x0000)."""
        self._values[self._keys.error_code] = 0
        self.following_error = False
        self.limits.reset()
        self.set_state(State402.SWITCH_ON_DISABLED)
        self._on_fault_reset()

    def set_sto(self, low: bool) -> None:
        """The STO input: low switches the power stage off (warning bit); the node sends
        the EMCY."""
        self.sto_low = low
        if low and self.state in VOLTAGE_STATES:
            self.set_state(State402.SWITCH_ON_DISABLED)
        else:
            self.set_state(self.state)  # warning bit

    # ------------------------------------------------------------------ each SYNC
    def command_joint(self, dt: float) -> None:
        """Write this joint's loop command for the next dynamics step."""
        dyn, j, values = self._dyn, self._j, self._values
        nm_per_permille = self._scale.nm_per_permille
        keys, limits = self._keys, self.limits
        dyn.torque_limit[j] = values[keys.max_torque] * nm_per_permille
        dyn.velocity_limit[j] = limits.velocity
        dyn.target_velocity[j] = 0.0
        dyn.torque_feedforward[j] = 0.0
        state = self.state
        if state not in POWERED or self.sto_low:
            dyn.mode[j] = _LOOP_OFF
            return
        if self._ramp_command(state, values[keys.controlword], dt):
            return
        if state != _ENABLED:  # quick stop active after its ramp: hold
            dyn.mode[j] = _LOOP_VELOCITY
            return
        bits = self._mode_command(values, dt)
        if bits is None:
            return
        if bits != self._mode_bits:
            self._mode_bits = bits
            self.set_state(self.state)

    def _ramp_command(self, state: State402, controlword: int, dt: float) -> bool:
        """Halt (controlword bit 8) starts a ramp, its release ends one; a running ramp
        commands this step (True)."""
        halt = bool(controlword & _CW_HALT)
        if state == _ENABLED and halt and not self._ramping:
            self._start_ramp(self._quick_stop_decel(), then=None)
        elif state == _ENABLED and not halt and self._ramping \
                and self._ramp_then is None:
            self._ramping = False  # halt released
        if not self._ramping:
            return False
        v = self._ramp_velocity
        step = self._ramp_decel * dt
        self._ramp_velocity = math.copysign(max(abs(v) - step, 0.0), v)
        if self._ramp_velocity == 0.0:
            self._ramp_zero_time += dt
        self._dyn.mode[self._j] = _LOOP_VELOCITY
        self._dyn.target_velocity[self._j] = self._ramp_velocity
        return True

    def _mode_command(self, values: dict[ObjectKey, Any], dt: float) -> int | None:
        """Operation enabled: the command of the mode of operation (0x6061); its statusword
        bits 12/13, or None when a following error faulted the drive (then commanded)."""
        dyn, j, keys, limits = self._dyn, self._j, self._keys, self.limits
        nm_per_permille = self._scale.nm_per_permille
        scale = self._scale.increments_per_rad
        mode = values[keys.mode_display]
        bits = 0
        if mode == _IP:
            if values[keys.controlword] & CW_BIT4:  # interpolation enabled: follow 0x60C1:1
                dyn.mode[j] = _LOOP_POSITION
                dyn.target_position[j] = limits.clamp(values[keys.interpolation_target] / scale)
                bits = SW_BIT12
            else:  # interpolation inactive: hold still
                dyn.mode[j] = _LOOP_VELOCITY
        elif mode == _PP:
            bits = self._profile_position(values, scale)
        elif mode == _HOMING:
            bits = self._homing(values, scale, dt)
        elif mode == _PV:
            self._velocity(values[keys.target_velocity] / scale)
        elif mode == _CSP:
            if not self._csp(values, scale, dt):
                return None
        elif mode == _CSV:
            self._velocity((values[keys.target_velocity] + values[keys.velocity_offset]) / scale)
            dyn.torque_feedforward[j] = values[keys.torque_offset] * nm_per_permille
        elif mode == _CST:
            self._cst((values[keys.target_torque] + values[keys.torque_offset])
                      * nm_per_permille)
        else:
            dyn.mode[j] = _LOOP_OFF  # no mode this drive runs selected: no torque
        return bits

    def _csp(self, values: dict[ObjectKey, Any], scale: float, dt: float) -> bool:
        """CSP: follow 0x607A with the offsets; False when the following error faulted the
        drive (its fault reaction's ramp is commanded from this step on)."""
        dyn, j, keys, limits = self._dyn, self._j, self._keys, self.limits
        demand = limits.clamp(values[keys.target_position] / scale)
        if limits.following_error(demand, float(dyn.position[j]), dt):
            self.following_error = True
            self.fault(cia301.EMCY_FOLLOWING_ERROR)
            self.command_joint(dt)
            return False
        dyn.mode[j] = _LOOP_POSITION
        dyn.target_position[j] = demand
        dyn.target_velocity[j] = values[keys.velocity_offset] / scale
        dyn.torque_feedforward[j] = values[keys.torque_offset] * self._scale.nm_per_permille
        return True

    def _cst(self, torque: float) -> None:
        """CST: the torque; beyond a software position limit the drive holds it."""
        dyn, j = self._dyn, self._j
        hold = self.limits.pushed_past(torque, float(dyn.position[j]))
        if hold is None:
            dyn.mode[j] = _LOOP_TORQUE
            dyn.torque_feedforward[j] = torque
        else:
            dyn.mode[j] = _LOOP_POSITION
            dyn.target_position[j] = hold

    def _velocity(self, target: float) -> None:
        """A velocity target (CSV, PV); towards a software position limit, a move to the
        limit no faster than the target (limits.py)."""
        dyn, j, limits = self._dyn, self._j, self.limits
        limit = limits.heading_to(target)
        if limit is None:
            dyn.mode[j] = _LOOP_VELOCITY
            dyn.target_velocity[j] = target
        else:
            dyn.mode[j] = _LOOP_POSITION
            dyn.target_position[j] = limit
            dyn.velocity_limit[j] = min(limits.velocity, abs(target))

    def _profile_position(self, values: dict[ObjectKey, Any], scale: float) -> int:
        """PP: a rising controlword bit 4 latches 0x607A (relative with bit 6) and is
        acknowledged by statusword bit 12 until bit 4 falls; the joint moves to the latched
        set-point no faster than 0x6081; bit 10 once it is there."""
        dyn, j = self._dyn, self._j
        cw = values[self._keys.controlword]
        rising = bool(cw & CW_BIT4) and not self._new_setpoint
        self._new_setpoint = bool(cw & CW_BIT4)
        if rising:
            target = values[self._keys.target_position] / scale
            if cw & CW_RELATIVE and self._pp_target is not None:
                target += self._pp_target
            self._pp_target = self.limits.clamp(target)
        q = float(dyn.position[j])
        goal = q if self._pp_target is None else self._pp_target
        limit = float(values[self._keys.profile_velocity]) / scale
        error = goal - q
        dyn.mode[j] = LoopMode.VELOCITY
        dyn.target_velocity[j] = max(-limit, min(limit, dyn.kp[j] * error))
        bits = SW_BIT12 if self._new_setpoint else 0
        if abs(error) * scale <= PP_WINDOW_INCREMENTS:
            bits |= c.SW_TARGET_REACHED
        return bits

    def _homing(self, values: dict[ObjectKey, Any], scale: float, dt: float) -> int:
        """Mode 6: a rising controlword bit 4 starts homing with 0x6098's method; after
        HOMING_TIME at standstill (a real drive searches its switch meanwhile) the reported
        position becomes the home offset 0x607C here: statusword bit 12 + 10. A method
        outside CiA 402's 1..37 ends in bit 13 (homing error)."""
        dyn, j = self._dyn, self._j
        dyn.mode[j] = LoopMode.VELOCITY  # held still
        cw = values[self._keys.controlword]
        rising = bool(cw & CW_BIT4) and not self._new_setpoint
        self._new_setpoint = bool(cw & CW_BIT4)
        if rising:
            self._homing_left = HOMING_TIME
        if self._homing_left is None:
            return self._mode_bits & (SW_BIT12 | c.SW_TARGET_REACHED | SW_HOMING_ERROR)
        if not 1 <= values[self._keys.homing_method] <= 37:
            self._homing_left = None
            return SW_HOMING_ERROR
        self._homing_left -= dt
        if self._homing_left > 0:
            return 0
        self._homing_left = None
        self.position_offset = (values[self._keys.home_offset]
                                - float(dyn.position[j]) * scale)
        return SW_BIT12 | c.SW_TARGET_REACHED

    def end_ramp(self) -> None:
        """After the dynamics step: a ramp with a next state ends at standstill."""
        if self._ramping and self._ramp_velocity == 0.0 and (
                abs(self._dyn.velocity[self._j]) < STOPPED_VELOCITY
                or self._ramp_zero_time >= STANDSTILL_TIME):
            then = self._ramp_then
            if then is not None:
                self._ramping = False
                self.set_state(then)
