"""What rocoma-can will do with one drive: its config measured against its EDS/DCF.

``plan_drive`` is called by check-config and by the hardware layer at start-up, so both say
the same thing: the modes the drive's 0x6502 lists, the feedback its objects allow, the PDOs
it lets us map (or its fixed ones), and what happens when the manager is lost. Missing
optional objects degrade explicitly (``notes``, printed by check-config and logged once at
start-up); anything that would make the drive unsafe or undrivable is a ValueError naming
the drive, the file and the object.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from ..files.capabilities import (
    MODE_NAMES,
    TARGET_OF_MODE,
    CapabilityError,
    DriveCapabilities,
    read_capabilities,
)
from ..files.identity import IdentityCheck
from ..protocol import cia301, cia402
from . import limits
from .config import FEEDBACK, DriveConfig
from .modes import DriveMode
from .pdo_layout import (
    ENTRY_OF_FEEDBACK,
    DriveLayout,
    LayoutPdo,
    always_on,
    check_against_od,
    layout_for,
)


@dataclass(frozen=True)
class DrivePlan:
    drive: DriveConfig          # the config with its feedback resolved against the file
    caps: DriveCapabilities
    layout: DriveLayout
    notes: tuple[str, ...]      # what is degraded, one sentence each
    guarded: bool = False       # watched by node guarding (0x100C/0x100D), not heartbeat
    leads_node: bool = True     # configures its node (NMT, heartbeat or guarding, consumer,
                                # unused PDOs): False for the higher axes of a shared node
    other_axes: tuple[int, ...] = ()  # the node's other axes (set on the one that leads)
    #: the limit objects bring-up writes, computed here once (limits.drive_writes)
    limit_writes: tuple[limits.LimitWrite, ...] = ()
    period: float | None = None  # s, the loop's the limits were computed for

    @property
    def identity(self) -> IdentityCheck:
        """What bring-up requires of the node's 0x1018 (checked by the node's lowest axis)."""
        return IdentityCheck.of(self.drive.identity, self.caps.object_dictionary,
                                self.caps.source)

    def report(self) -> list[str]:
        """check-config's lines for this drive."""
        d, lay = self.drive, self.layout

        def entries(p: LayoutPdo) -> str:  # a fixed RPDO's constants with the value sent
            return ", ".join(e.name if e.constant is None else f"{e.name} = {e.constant}"
                             for e in p.entries)
        pdos = "; ".join(f"{'fixed ' if p.fixed else ''}RPDO{p.number} [{entries(p)}]"
                         for p in lay.rpdos)
        pdos += "; " + "; ".join(f"{'fixed ' if p.fixed else ''}TPDO{p.number} "
                                 f"[{', '.join(p.names)}]" for p in lay.tpdos)
        axis = f" axis {d.axis}" if d.axis > 1 else ""
        lines = [f"{d.name} (node {d.node_id}{axis}, {self.caps.source}):",
                 f"  modes {', '.join(m.name for m in d.modes)}; feedback "
                 f"{', '.join(d.feedback or ()) or 'statusword only'}",
                 f"  {pdos}"]
        lines += [f"  {line}" for line in self.caps.report(self.guarded)]
        lines += [f"  {line}" for line in limits.report(d, self.limit_writes, self.period)]
        lines.append(f"  {self.identity.describe()}"
                     + ("" if self.leads_node else " (the node's: checked by its lowest axis)"))
        lines += [f"  note: {n}" for n in self.notes]
        return lines


def plan_drives(drives: Sequence[DriveConfig], first_bus: str = "", *,
                period: float | None = None) -> list[DrivePlan]:
    """Every drive's plan (``plan_drive``, at the loop's ``period``). The axes of one node
    share its PDO channels:
    planned in axis order, each takes from the channels the ones before it left; then each
    keeps only its own, so its bring-up configures those alone, and the node's lowest axis
    (``leads_node``) also switches off the channels no axis uses."""
    plans: list[DrivePlan | None] = [None] * len(drives)
    nodes: dict[tuple[str, int], list[int]] = {}
    for i, d in enumerate(drives):
        nodes.setdefault((d.bus or first_bus, d.node_id), []).append(i)
    for members in nodes.values():
        members.sort(key=lambda i: drives[i].axis)
        taken: set[tuple[bool, int]] = set()
        for i in members:
            planned = plan_drive(drives[i], frozenset(taken), period=period)
            taken |= _channels_of(planned.layout)
            plans[i] = planned
        if len(members) > 1:
            for k, i in enumerate(members):
                plan = plans[i]
                assert plan is not None
                own = _channels_of(plan.layout)
                every = {(ch.tx, ch.number) for ch in plan.caps.rpdos + plan.caps.tpdos}
                drop = (taken if k == 0 else every) - own
                others = tuple(drives[j].axis for j in members[1:]) if k == 0 else ()
                plans[i] = dataclasses.replace(plan, caps=_without(plan.caps, drop),
                                               leads_node=k == 0, other_axes=others)
    return [p for p in plans if p is not None]


def notes_with_drives(plans: Sequence[DrivePlan]) -> list[tuple[str, str]]:
    """Every drive's notes, each said once: (note, "drive 'j1'" or "drives 'j1', 'j2'"),
    in the order first met. Drives of one model share their notes; a line per drive
    said the same thing once per drive at each start (six lines for two drives)."""
    drives: dict[str, list[str]] = {}
    for plan in plans:
        for note in plan.notes:
            drives.setdefault(note, []).append(repr(plan.drive.name))
    return [(note, ("drive " if len(names) == 1 else "drives ") + ", ".join(names))
            for note, names in drives.items()]


def _channels_of(layout: DriveLayout) -> set[tuple[bool, int]]:
    return {(False, p.number) for p in layout.rpdos} | {(True, p.number) for p in layout.tpdos}


def _without(caps: DriveCapabilities, channels: Iterable[tuple[bool, int]]) -> DriveCapabilities:
    drop = set(channels)
    return dataclasses.replace(
        caps, rpdos=tuple(ch for ch in caps.rpdos if (False, ch.number) not in drop),
        tpdos=tuple(ch for ch in caps.tpdos if (True, ch.number) not in drop))


def plan_drive(drive: DriveConfig, taken: frozenset[tuple[bool, int]] = frozenset(), *,
               period: float | None = None) -> DrivePlan:
    """Measure one drive's config against its file; ValueError with every problem found.
    ``taken``: PDO channels (is a TPDO, number) other axes of its node use already.
    ``period``: the loop's (s), which the limits in time are computed for (0x6066: the
    plan's ``limit_writes``, what bring-up writes); None where no loop will run it (a
    file's fit), which leaves those out."""
    where = f"drive {drive.name!r}"
    caps = _capabilities(drive, taken, where)
    problems: list[str] = []
    notes: list[str] = list(caps.file_notes)
    commissioned = caps.commissioned_node_id
    if commissioned is not None and commissioned != drive.node_id:
        notes.append(f"a DCF commissioned for node {commissioned}, used for node "
                     f"{drive.node_id}: its values are taken, its node's COB-IDs are not")
    if caps.device_type is not None and caps.device_type & 0xFFFF != 402:
        problems.append(f"{caps.source} is not a CiA 402 drive's (0x1000 = "
                        f"0x{caps.device_type:08X})")
    guarded = _guarding(drive, caps, problems, notes)
    problems += _mode_problems(drive, caps)
    _mode_objects(drive, caps, problems, notes)
    feedback = _feedback(drive, caps, problems, notes)
    for index, sub, what in ((cia402.POSITION_ENCODER_RESOLUTION, 1, "increments_per_rev"),
                             (cia402.GEAR_RATIO, 1, "gear_ratio"),
                             (cia402.RATED_TORQUE, 0, "rated_torque_nm")):
        if not caps.has(index, sub):
            notes.append(f"no 0x{index:04X}: {what} comes from the config alone (the drive "
                         "cannot confirm it)")
    _manager_loss(drive, caps, guarded, problems, notes)
    writes: list[limits.LimitWrite] = []
    try:
        writes = limits.drive_writes(drive, caps, period)
    except ValueError as exc:
        problems.append(str(exc).removeprefix(f"{where}: "))
    if problems:
        raise ValueError(f"{where}: " + "; ".join(problems))
    resolved, layout = _fit_feedback(drive, feedback, caps, notes)
    check_against_od(layout, caps.object_dictionary, drive.name)
    notes += always_on(layout, caps)
    return DrivePlan(resolved, caps, layout, tuple(notes), guarded,
                     limit_writes=tuple(writes), period=period)


def _capabilities(drive: DriveConfig, taken: frozenset[tuple[bool, int]],
                  where: str) -> DriveCapabilities:
    """The drive's file read at its axis, without the PDO channels its node's other axes
    use (``taken``; an axis above 1 cannot use a fixed mapping, which names axis 1's
    objects); ValueError when it has none of a kind left."""
    try:
        caps = read_capabilities(drive.eds, drive.node_id, drive.axis)
    except CapabilityError as exc:
        raise ValueError(f"{where}: {exc}") from None
    if drive.axis > 1:  # a fixed mapping names the objects of the axis it was made for
        taken |= {(ch.tx, ch.number) for ch in caps.rpdos + caps.tpdos
                  if not ch.mapping_writable}
    if not taken:
        return caps
    left = _without(caps, taken)
    for kind, before, after in (("RPDOs", caps.rpdos, left.rpdos),
                                ("TPDOs", caps.tpdos, left.tpdos)):
        if not after:
            raise ValueError(f"{where}: no {kind} left for axis {drive.axis}: the node's "
                             f"other axes use {', '.join(ch.name for ch in before)}"
                             + (" (a fixed mapping serves axis 1 only)"
                                if any(not ch.mapping_writable for ch in before) else ""))
    return left


def _mode_objects(drive: DriveConfig, caps: DriveCapabilities, problems: list[str],
                  notes: list[str]) -> None:
    """How the drive's mode is set (0x6060: by PDO, or once by SDO), its interpolation
    period (0x60C2) and homing method (0x6098)."""
    if not caps.writable(cia402.MODES_OF_OPERATION):
        # not even by SDO: the drive would run whatever mode it powers up in
        problems.append(f"0x6060 (modes of operation): {caps.source} "
                        + ("has no 0x6060:0" if not caps.has(cia402.MODES_OF_OPERATION)
                           else "gives 0x6060:0 no write access")
                        + f", so mode {drive.modes[0].name} cannot be set (by PDO or SDO)")
    elif len(drive.modes) > 1 and not caps.carries(cia402.MODES_OF_OPERATION):
        problems.append(f"0x6060 (modes of operation): "
                        f"{caps.why_not_carried(cia402.MODES_OF_OPERATION)}, so the mode is "
                        "set once by SDO at start-up and cannot change in the cycle: "
                        f"configure one mode, not {[m.name for m in drive.modes]}")
    elif not caps.carries(cia402.MODES_OF_OPERATION):
        notes.append(f"no RPDO can carry 0x6060: mode {drive.modes[0].name} is set by SDO at "
                     "start-up, before enabling")
    if DriveMode.IP in drive.modes and not caps.writable(cia402.INTERPOLATION_PERIOD, 1):
        notes.append("IP without a writable 0x60C2: the drive interpolates over its own "
                     "period, which must equal the loop's")
    if drive.homing_method is not None and not caps.writable(cia402.HOMING_METHOD):
        problems.append(f"homing_method {drive.homing_method}: {caps.source} has no "
                        "writable 0x6098 (homing method)")


def _feedback(drive: DriveConfig, caps: DriveCapabilities, problems: list[str],
              notes: list[str]) -> tuple[str, ...]:
    """The feedback the drive reports: the config's (each must exist), or every kind its
    file has (the others said in a note)."""
    available = tuple(f for f in FEEDBACK if caps.has(ENTRY_OF_FEEDBACK[f].index))
    if drive.feedback is None:
        for f in FEEDBACK:
            if f not in available:
                notes.append(f"no 0x{ENTRY_OF_FEEDBACK[f].index:04X}: {f} feedback off "
                             f"(JointState.{f} stays 0)")
        return available
    for f in drive.feedback:
        if f not in available:
            problems.append(f"feedback {f!r}: the drive has no "
                            f"0x{ENTRY_OF_FEEDBACK[f].index:04X}")
    return drive.feedback


def _manager_loss(drive: DriveConfig, caps: DriveCapabilities, guarded: bool,
                  problems: list[str], notes: list[str]) -> None:
    """What the drive does when the manager dies or hangs: a drive nothing switches off
    then is a problem unless its config accepts the risk."""
    if not caps.supervised(guarded):
        if drive.accept_unsupervised:
            notes.append("RISK accepted (accept_unsupervised): if the manager dies or hangs, "
                         "this drive keeps its last command until its own limits stop it")
        else:
            problems.append("losing the manager would leave this drive running: its file has "
                            "no writable heartbeat consumer (0x1016) or life guarding "
                            "(0x100C/0x100D) with 0x6007 or 0x1029 behind it; set "
                            "accept_unsupervised: true to run it anyway, with "
                            "that risk")
    elif not caps.abort_connection:
        notes.append("no 0x6007: on manager loss the drive's heartbeat consumer (or life "
                     "guarding) makes it "
                     "leave OPERATIONAL (0x1029) and stop applying RPDOs; whether it also "
                     "switches its power stage off is its vendor's choice")


def _guarding(drive: DriveConfig, caps: DriveCapabilities, problems: list[str],
              notes: list[str]) -> bool:
    """Whether the manager watches the drive by node guarding instead of its heartbeat. A
    drive with neither is a problem: the manager would not see it leave OPERATIONAL (a
    reboot, an NMT stop from another node) and would not hear it when it stops sending."""
    heartbeat = caps.writable(cia301.PRODUCER_HEARTBEAT_TIME)
    guarding = caps.node_guarding
    if drive.guarding == "heartbeat" and not heartbeat:
        problems.append(f"guarding: heartbeat, but {caps.source} has no writable heartbeat "
                        "producer (0x1017)" + ("; it has node guarding (guarding: "
                                               "node_guarding)" if guarding else ""))
    elif drive.guarding == "node_guarding" and not guarding:
        problems.append(f"guarding: node_guarding, but {caps.source} has no writable guard "
                        "time and life time factor (0x100C/0x100D)")
    elif drive.guarding == "auto" and not (heartbeat or guarding):
        problems.append(f"{caps.source} has neither a writable heartbeat producer (0x1017) "
                        "nor node guarding (0x100C/0x100D): rocoma-can must see every "
                        "drive's life")
    guarded = guarding and (drive.guarding == "node_guarding" or (
        drive.guarding == "auto" and caps.guarded_by_default()))
    if guarded and not heartbeat and caps.value(cia301.PRODUCER_HEARTBEAT_TIME):
        problems.append(f"{caps.source} has a read-only heartbeat producer (0x1017 = "
                        f"{caps.value(cia301.PRODUCER_HEARTBEAT_TIME)}): a node that sends "
                        "heartbeats does not answer node guarding (CiA 301)")
    if guarded and drive.guarding == "auto":
        why = "no heartbeat producer (0x1017)" if not heartbeat else \
            "no heartbeat consumer (0x1016): guarding is how it watches the manager"
        notes.append(f"{why}: node guarding, the manager asks every {drive.heartbeat_ms} ms "
                     "(0x100C) and the drive watches the asking (0x100D)")
    return guarded


def _mode_problems(drive: DriveConfig, caps: DriveCapabilities) -> list[str]:
    """Each configured mode must be one the drive has (0x6502, or its target objects where
    the file gives 0x6502 no value) and whose target an RPDO can carry."""
    problems = []
    usable = [MODE_NAMES[m] for m in TARGET_OF_MODE if caps.usable(m)]
    for mode in drive.modes:
        if not caps.supports(int(mode)):
            source = (f"its 0x6502 = 0x{caps.supported_modes:X}" if caps.modes_stated
                      else "its target objects (0x6502 has no value in the file)")
            problems.append(f"mode {mode.name} is not supported: {source} lists "
                            f"{', '.join(caps.mode_names) or 'none'}")
        elif not caps.usable(int(mode)):
            index, sub = TARGET_OF_MODE[int(mode)]
            problems.append(f"mode {mode.name} needs its target 0x{index:04X}:{sub} in an "
                            f"RPDO, but {caps.why_not_carried(index, sub)}; modes it can "
                            f"run: {', '.join(usable) or 'none'}")
    return problems


def _fit_feedback(drive: DriveConfig, feedback: tuple[str, ...], caps: DriveCapabilities,
                  notes: list[str]) -> tuple[DriveConfig, DriveLayout]:
    """The layout for the drive's feedback; where the config leaves feedback to the file and
    its TPDOs cannot carry all of it, the least needed goes first (torque, then velocity:
    the shipped controllers need position and velocity), said in a note. A controller that
    needs what was left out is refused when the controllers are loaded."""
    option = feedback
    while True:
        resolved = dataclasses.replace(drive, feedback=option)
        try:
            layout = layout_for(resolved, caps)
            break
        except ValueError:
            if drive.feedback is not None or len(option) <= 1 \
                    or not _tpdo_short(resolved, caps):
                raise
            option = option[:-1]
    if option != feedback:
        notes.append(f"its TPDOs carry statusword and {', '.join(option)} only: "
                     f"{', '.join(f for f in feedback if f not in option)} feedback left "
                     "out (JointState stays 0 there)")
    return resolved, layout


def _tpdo_short(drive: DriveConfig, caps: DriveCapabilities) -> bool:
    """The layout fails on the TPDO side alone (the RPDOs fit)."""
    try:
        layout_for(dataclasses.replace(drive, feedback=()), caps)
    except ValueError:
        return False
    return True



def pdo_bytes_problem(drive: DriveConfig, bus: str, fd: bool) -> str | None:
    """Why the drive's PDOs cannot go on its bus, or None: a classic frame carries 8 bytes."""
    if drive.pdo_bytes <= 8 or fd:
        return None
    return (f"{drive.pdo_bytes} bytes a PDO need a CAN FD bus (fd: true), and bus {bus!r} is "
            "classic CAN (8 bytes a frame)")


def check_pdo_bytes(drives: Sequence[DriveConfig], buses: Sequence[tuple[str, bool]]) -> None:
    """ValueError for the first drive whose PDOs its bus cannot carry; ``buses``: each
    drive's bus, its name and whether it is CAN FD."""
    for drive, (bus, fd) in zip(drives, buses):
        why = pdo_bytes_problem(drive, bus, fd)
        if why is not None:
            raise ValueError(f"drive {drive.name!r}: pdo_bytes: {why}")


def pdo_using(cob_id: int, plans: Sequence[DrivePlan]) -> str | None:
    """Which drive's PDO uses ``cob_id`` (an absolute COB-ID from its EDS/DCF), or None."""
    for plan in plans:
        for pdo in (*plan.layout.rpdos, *plan.layout.tpdos):
            if pdo.cob_id == cob_id:
                return f"a PDO of drive {plan.drive.name!r}"
    return None
