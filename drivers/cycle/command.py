"""From the active layer's JointCommand to each drive's controlword, mode and targets.

Runs while the manager is OK or EMERGENCY (FAILPROOF never gets here: frames_out.py). Per
drive, in this order: a homing job runs its own frames (homing.py); a drive not under command
(not READY, latched, or not armed) gets torque-off; a cyclic mode steps the enable sequence
(enable.py) and holds the actual position until operation enabled, then sends the targets
(PP through its set-point handshake, IP with the interpolation bit); torque-off and quick
stop are sent as such. A drive is armed when a switch commits with it READY: one that comes
back later (a recovery, a late start) stays off until the next switch, since that controller
never saw it. The manager's two checks on JointCommand (``limit_command``, every cycle, and
``neutral_command``, on every fall to a lower layer) live here too.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ..bringup.drive_bringup import BringupPhase, DriveBringup
from ..plan.modes import CW_ENABLE_INTERPOLATION, KIND, DriveMode, SetPointHandshake, carrier
from ..plan.scaling import Scaling
from ..protocol import cia402
from ..protocol.joints import JointCommand, JointMode, JointState
from .drive_table import DriveTable
from .enable import OP_ENABLED, EnableSequence
from .frames_out import FramesOut
from .homing import HOMING_MODE, HomingJob, HomingQueue
from .supervision import FollowingErrorWatch, Supervisor

_CW_QUICK_STOP = int(cia402.Controlword.QUICK_STOP)
_CYCLIC = (int(JointMode.CSP), int(JointMode.CSV), int(JointMode.CST))
_PP, _IP, _CSP = int(DriveMode.PP), int(DriveMode.IP), int(DriveMode.CSP)


class Commands:
    """The command side of N drives: what ``send`` puts in their RPDOs each cycle."""

    def __init__(self, table: DriveTable, *, state: JointState, command: JointCommand,
                 raw: dict[str, np.ndarray], scaling: Scaling, supervisor: Supervisor,
                 enable: EnableSequence, frames: FramesOut,
                 ready: Callable[[], np.ndarray]) -> None:
        """``raw``: the raw bus values, one slot per drive (targets are encoded into them);
        ``ready``: per drive, READY without a latched fault (read at a switch)."""
        drives = [d.config for d in table]
        n = len(drives)
        self._state, self._command, self._raw = state, command, raw
        self._scaling, self._sup, self.enable, self._frames = scaling, supervisor, enable, frames
        self.homing = HomingQueue(n)
        self._allowed_modes = np.array(
            [(1 << JointMode.TORQUE_OFF) | (1 << JointMode.QUICK_STOP)
             | sum(1 << int(KIND[m]) for m in d.modes) for d in drives], dtype=np.int64)
        self._allowed = self._allowed_modes.tolist()
        # the 0x6060 value that carries each commanded JointMode, per drive (modes.py)
        self._carrier = [carrier(d.modes) for d in drives]
        self._pp = [DriveMode.PP in d.modes for d in drives]  # the set-point handshake
        self._setpoints = SetPointHandshake(n)
        self._default_mode = [int(d.modes[0]) for d in drives]
        # per drive: its TPDOs carry the actual position (a neutral command holds it)
        self._position_fed = np.array([d.layout.maps("position") for d in table], dtype=bool)
        self._ready = ready
        self.following = FollowingErrorWatch(drives, self._position_fed)
        self._mode_bits = np.zeros(n, dtype=np.int64)
        self._ones = np.ones(n, dtype=np.int64)
        self._finite = np.zeros(n, dtype=bool)
        self._armed = [False] * n
        self._switches_seen = -1

    def reset(self, i: int) -> None:
        """Drive i is not under command: its enable sequence and set-point start over."""
        self.enable.reset(i)
        self.following.tracking[i] = False
        if self._pp[i]:
            self._setpoints.reset(i)

    def disarm(self, i: int) -> None:
        self._armed[i] = False

    def send(self, bringup: Sequence[DriveBringup], now: float,
             switch_count: int | None) -> None:
        """This cycle's frames of every configured drive. ``switch_count``: the manager's
        committed switches (None: no manager, every READY drive is under command)."""
        cmd, raw, sc, sup, frames = self._command, self._raw, self._scaling, self._sup, \
            self._frames
        following = self.following
        following.check(self._state.position, sup, now)  # last cycle's CSP targets
        sc.encode_position(cmd.position, raw["target_position"])
        sc.encode_velocity(cmd.velocity, raw["target_velocity"])
        sc.encode_torque(cmd.torque, raw["target_torque"])
        modes = cmd.mode.tolist()
        states = self._state.cia402_state.tolist()
        tpos, tvel = raw["target_position"].tolist(), raw["target_velocity"].tolist()
        ttrq, actual = raw["target_torque"].tolist(), raw["position"].tolist()
        statuswords = raw["statusword"]
        enable = self.enable
        armed = self._armed_for(switch_count)
        homing = self.homing.jobs
        self.homing.take()
        for i, b in enumerate(bringup):
            if not b.mapped:
                continue
            job = homing[i]
            if job is not None:
                if self._home_step(i, b, job, states[i], now):
                    continue  # this cycle's homing frames are out
                homing[i] = None  # done: torque-off until the next switch (new reference)
                if armed is not None:
                    armed[i] = False
            if (b.phase != BringupPhase.READY or sup.latched[i] is not None
                    or (armed is not None and not armed[i])):
                if armed is not None:  # off until the next switch: a drive that comes back
                    armed[i] = False   # (a recovery) never takes up a command it dropped
                frames.off(i, b)
                self.reset(i)
                continue
            mode, st = modes[i], states[i]
            values: tuple[int, ...]
            if mode in _CYCLIC and not self._allowed[i] >> mode & 1:
                # limit_command stops this before it gets here; if a caller skipped it, the
                # drive's RPDO has no target for this mode: never send it, stop instead.
                sup.fault(i, f"commanded {JointMode(mode).name}, which it is not configured "
                             "for", now)
                mode = int(JointMode.TORQUE_OFF)
            if mode in _CYCLIC:
                cw = enable.controlword(i, st, now)
                carried = self._carrier[i][mode]
                if self._pp[i] and (st != OP_ENABLED or carried != _PP):
                    self._setpoints.reset(i)  # the next PP target is a new set-point
                if st != OP_ENABLED:  # enabling (or dropped out): hold the actual position
                    values = (cw, carried, actual[i], 0, 0)
                elif carried == _PP:
                    bits, target = self._setpoints.step(i, tpos[i], int(statuswords[i]))
                    values = (cw | bits, carried, target, tvel[i], ttrq[i])
                else:
                    if carried == _IP:
                        cw |= CW_ENABLE_INTERPOLATION
                    elif carried == _CSP:
                        following.tracking[i] = True
                    values = (cw, carried, tpos[i], tvel[i], ttrq[i])
            else:
                cw = _CW_QUICK_STOP if mode == JointMode.QUICK_STOP else 0
                values = (cw, self._default_mode[i], actual[i], 0, 0)
                self.reset(i)
            frames.rpdos(i, values)
        following.sent(cmd.position)

    def _armed_for(self, switch_count: int | None) -> list[bool] | None:
        """Per drive, whether it is under command this cycle (None: no manager, every
        READY drive is); a switch committed since the last cycle arms who is ready."""
        if switch_count is None:
            return None
        if switch_count != self._switches_seen:
            self._switches_seen = switch_count
            self._armed = self._ready().tolist()
        return self._armed

    def _home_step(self, i: int, b: DriveBringup, job: HomingJob, state: int,
                   now: float) -> bool:
        """One cycle of drive i's homing: True when its frames were sent, False when the job
        has ended (the caller then treats the drive as usual)."""
        if job.done():
            return False
        if b.phase != BringupPhase.READY or self._sup.latched[i] is not None:
            job.fail("the drive faulted or left start-up state READY")
            return False
        cw = self.enable.controlword(i, state, now)
        homing_cw = job.step(state == OP_ENABLED, int(self._raw["statusword"][i]), now)
        if job.done():
            self.enable.reset(i)
            return False
        self._frames.rpdos(i, (homing_cw if homing_cw is not None else cw, HOMING_MODE,
                               int(self._raw["position"][i]), 0, 0))
        return True

    # --- the manager's checks on JointCommand ---------------------------------------------
    def limit_command(self, command: JointCommand) -> bool:
        """False (-> failure -> e-stop) for a mode a drive is not configured for, or NaN/inf.

        Finite targets are clipped in place to the configured joint limits.
        """
        mode = command.mode
        if max(mode.tolist()) > 15:  # Python's max on a dozen: cheaper than numpy's
            return False
        np.left_shift(self._ones, mode, out=self._mode_bits)
        np.bitwise_and(self._mode_bits, self._allowed_modes, out=self._mode_bits)
        if np.count_nonzero(self._mode_bits) != len(self._mode_bits):
            return False
        if not (self._all_finite(command.position) and self._all_finite(command.velocity)
                and self._all_finite(command.torque)):
            return False
        self._scaling.clip_command(command.position, command.velocity, command.torque)
        return True

    def _all_finite(self, targets: np.ndarray) -> bool:
        """isfinite into a preallocated buffer, not a sum: inf + -inf would warn (and
        allocate); the look at a dozen bools in Python, cheaper than numpy's ``all``."""
        np.isfinite(targets, out=self._finite)
        return False not in self._finite.tolist()

    def neutral_command(self, command: JointCommand) -> None:
        """Targets for the fields a lower layer does not write itself: velocity and torque
        0; the position target at the actual position where the drive reports it (else
        the previous target when it is finite, else that joint quick-stops in firmware).
        The manager calls it on every fall to a lower layer, before the emergency
        controller writes, so the failed controller's targets (or its NaNs) are never sent
        in fields the emergency controller leaves alone. The emergency controller still
        owns its command: torque 0 in CST is no holding torque."""
        position = command.position
        np.copyto(position, self._state.position, where=self._position_fed)
        finite = self._finite
        np.isfinite(position, out=finite)
        if not finite.all():  # a fault path, rare: allocation is fine here
            stuck = ~finite
            position[stuck] = 0.0
            command.mode[stuck] = JointMode.QUICK_STOP
        command.velocity.fill(0.0)
        command.torque.fill(0.0)
