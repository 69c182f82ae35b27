"""The demo's drives and config: the robot ``rocoma-can demo`` runs (six simulated drives
by default), fitted to a vendor's EDS/DCF with ``--eds`` (``emulate``: the modes the file can
run, its scaling, its node id, every axis of a multi-axis device). Tests build their
runtimes from ``demo_config`` too: one robot, one set of margins for a busy machine."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

MANAGER_ID = 100
#: the demo's buses: drivers/link/inproc.py, which copies a frame once per send, not once per
#: receiver as python-can's virtual does (the demo has 3-4 receivers per bus)
DEFAULT_INTERFACE = "inproc"
ESTOP_COB_ID = 0x0A0
ZENOH_PREFIX = "rocoma/demo"
#: the walk-through's pauses, in shares of --duration, in the order they come: after the
#: switch to pd, to trajectory, the first fault, the second, the final switch, the e-stop
PAUSES = (1.0, 1.0, 0.5, 0.5, 1.0, 0.5)
MIN_PAUSE = 0.2  # s per share: each step is seen to hold for a while, however short the demo
#: the demo's drives, as demo_config builds them (emulate measures one against the file)
DRIVE = {"increments_per_rev": 1048576, "rated_torque_nm": 1.0, "heartbeat_ms": 100}
#: ``demo --fd``: the bit rates of the CAN FD buses its in-process ones stand for (the
#: arbitration phase; the data phase at --data-bitrate), and the PDOs its drives map there
FD_BITRATE = 1_000_000
FD_DATA_BITRATE = 5_000_000
FD_PDO_BYTES = 64


def default_buses(drives: int) -> int:
    """One bus up to six drives; beyond, a bus per three drives, as a robot with one bus per
    limb has (a classic 1 Mbit/s bus carries ~7,400 frames/s: a few drives at 1 kHz)."""
    return 1 if drives <= 6 else -(-drives // 3)


@dataclass
class Emulated:
    """The demo's drives fitted to a drive's EDS/DCF (``--eds``): what the file allows."""
    eds: str
    modes: list[str]
    emergency: dict[str, Any]
    drive: dict[str, Any]              # DriveConfig fields: eds, scaling, ...
    first_node: int = 1                # a DCF's commissioned node id
    axes: int = 1                      # axes per node (a multi-axis device: CiA 402-2)
    notes: list[str] = field(default_factory=list)
    segment: dict[str, Any] = field(default_factory=dict)  # SimulatedSegment keywords


def emulate(path: str, drives: int) -> Emulated:
    """Fit the demo to ``path``: the position mode it supports (CSP, else IP, else PP), CST
    for the emergency controller damp where it has it (else hold in the position mode),
    its scaling, its node id if it is a DCF. ValueError when no position mode fits."""
    from ...drivers.files.capabilities import CapabilityError, read_capabilities
    from ...drivers.protocol.cia402 import (
        CONTROLWORD,
        GEAR_RATIO,
        MAX_AXES,
        MODES_OF_OPERATION,
        POSITION_ENCODER_RESOLUTION,
        QUICK_STOP_DECELERATION,
        RATED_TORQUE,
        on_axis,
    )
    try:
        caps = read_capabilities(path, 1)
    except CapabilityError as exc:
        raise ValueError(str(exc)) from None
    notes = []
    position = next((m for m in ("csp", "ip", "pp") if caps.usable(_MODE_NUMBER[m])), None)
    if position is None:
        raise ValueError(f"{path}: no position mode the demo's controllers can use (it has "
                         f"{', '.join(caps.mode_names) or 'no mode'}; needs CSP, IP or PP with "
                         "a target an RPDO can carry)")
    modes = [position]
    mode_in_pdo = caps.carries(MODES_OF_OPERATION) and all(
        ch.mapping_writable or ch.maps(MODES_OF_OPERATION) for ch in caps.rpdos)
    if caps.usable(_MODE_NUMBER["cst"]) and mode_in_pdo:
        modes.append("cst")
        emergency = {"name": "damp", "plugin": "damp",
                     "params": {"damping": 0.05, "still_time": 0.2, "timeout": 2.0}}
    else:
        emergency = {"name": "hold", "plugin": "hold", "params": {"mode": "CSP"}}
        notes.append("no CST it can switch to in the cycle: the emergency controller is hold "
                     f"(position targets, carried in {position.upper()}), not damp")
    increments, revs = (caps.value(POSITION_ENCODER_RESOLUTION, 1),
                        caps.value(POSITION_ENCODER_RESOLUTION, 2))
    # without 0x608F a file's ramps (0x6084/0x6085) are in units the demo cannot know
    per_rev = int(increments // revs) if increments and revs else 1 << 12
    if per_rev < 1:
        raise ValueError(f"0x608F (position encoder resolution) is {increments} increment(s) "
                         f"per {revs} revolutions: less than one a revolution, which no joint "
                         "scaling can use")
    overrides: dict[tuple[int, int], int] = {}
    if not (increments and revs) and caps.has(QUICK_STOP_DECELERATION):
        overrides[(QUICK_STOP_DECELERATION, 0)] = 10 * per_rev
        notes.append("its ramps are in units it does not state (no 0x608F): the simulated "
                     "drives stop at 10 turns/s² (0x6085)")
    motor, shaft = caps.value(GEAR_RATIO, 1), caps.value(GEAR_RATIO, 2)
    rated = caps.value(RATED_TORQUE) or 1000
    if rated < 0:
        raise ValueError(f"0x6076 (rated torque) is {rated}: no torque can be scaled by it")
    drive = {"eds": path, "increments_per_rev": per_rev, "rated_torque_nm": rated / 1000.0,
             "gear_ratio": motor / shaft if motor and shaft else 1.0}
    if not caps.supervised():
        drive["accept_unsupervised"] = True
        notes.append("the file gives no way to make a drive let go of a lost manager: "
                     "accepted for this simulation only")
    fitted = Emulated(path, modes, emergency, drive, notes=notes,
                      segment={"eds_path": path, "increments_per_rev": per_rev,
                               "overrides": overrides,
                               "rated_torque_nm": rated / 1000.0})
    if caps.commissioned_node_id is not None:
        fitted.first_node = caps.commissioned_node_id
        notes.append(f"a DCF of node {caps.commissioned_node_id}: the drives from node "
                     f"{caps.commissioned_node_id} on, each with its COB-IDs re-derived")
    # One drive measured against the file says what would be wrong with every drive: once,
    # about the file, not once per drive of the config.
    from ...drivers.plan.config import DriveConfig
    from ...drivers.plan.drive_plan import plan_drive, plan_drives

    def axis(n: int) -> DriveConfig:
        return DriveConfig.from_dict({"name": f"joint{n}", "node_id": fitted.first_node,
                                      "modes": modes, "axis": n, **DRIVE, **drive})
    try:
        plan_drive(axis(1))
    except ValueError as exc:
        raise ValueError(str(exc).removeprefix("drive 'joint1': ")) from None
    # A multi-axis device: the demo drives every axis it can share the node's PDOs out to
    while fitted.axes < MAX_AXES and caps.has(on_axis(CONTROLWORD, fitted.axes + 1)):
        try:
            plan_drives([axis(n) for n in range(1, fitted.axes + 2)])
        except ValueError as exc:
            why = str(exc).removeprefix(f"drive 'joint{fitted.axes + 1}': ").split("; ")[0]
            notes.append(f"axis {fitted.axes + 1} not driven: {why}")
            break
        fitted.axes += 1
    if fitted.axes > 1:
        notes.append(f"{fitted.axes} axes per node (CiA 402-2): each axis a joint, "
                     f"axis n's objects at + (n - 1) x 0x800")
    return fitted


_MODE_NUMBER = {"csp": 8, "ip": 7, "pp": 1, "cst": 10}


def demo_config(channel: str, drives: int, rate: float, buses: int = 1,
                interface: str = "virtual", emulated: Emulated | None = None,
                data_bitrate: int | None = None,
                priority: int | None = None) -> dict[str, Any]:
    """The demo's config: ``buses`` > 1 gives channels ``channel-0`` ... each with its share
    of the drives (node ids from 1 on each bus); ``interface`` is an in-process one
    (python-can's ``virtual``, or ``inproc``, drivers/link/inproc.py); ``emulated``: drives
    fitted to a vendor file (``emulate``); ``data_bitrate``: CAN FD buses of FD_BITRATE
    and this data bit rate, load-checked as such, whose drives map PDOs of up to
    FD_PDO_BYTES (one RPDO and one TPDO a cycle). Without it the buses have no bit rate:
    an in-process bus carries any load. ``priority``: the loop's ``realtime.priority``
    (SCHED_FIFO); None, the demo's default, runs it at normal priority."""
    joints = [f"joint{i}" for i in range(1, drives + 1)]
    per_bus = -(-drives // buses)
    modes = emulated.modes if emulated else ["csp", "cst"]
    emergency = emulated.emergency if emulated else {
        "name": "damp", "plugin": "damp",
        "params": {"damping": 0.05, "still_time": 0.2, "timeout": 2.0}}
    drive = emulated.drive if emulated else {}
    first_node = emulated.first_node if emulated else 1
    axes = emulated.axes if emulated else 1
    fd: dict[str, Any] = {} if data_bitrate is None else {
        "bitrate": FD_BITRATE, "fd": True, "data_bitrate": data_bitrate}
    if data_bitrate is not None:
        drive = {**drive, "pdo_bytes": FD_PDO_BYTES}
    if buses == 1:
        bus_section: dict[str, Any] = {"bus": {"interface": interface, "channel": channel,
                                               **fd}}
    else:
        bus_section = {"buses": [{"name": f"bus{k}", "interface": interface,
                                  "channel": f"{channel}-{k}", **fd} for k in range(buses)]}
    return {
        **bus_section,
        "rate": rate,
        "manager": {"node_id": MANAGER_ID, "heartbeat_ms": 100, "estop_cob_id": ESTOP_COB_ID,
                    "estop_must_be_cleared": True, "status_period": 0.2},
        # The demo runs without real-time priority beside its simulated drives on whatever
        # the machine is doing: a controller call preempted past its budget (0.5 cycles by
        # default), or TPDOs late for 5 cycles, would be taken as a controller's or a
        # drive's failure. A second and a half for calls and TPDOs, drive heartbeats and
        # the drives' consumer of the manager's, and a hang after two seconds, keep the
        # walk-through about what it shows on a busy machine (two CPU hogs stalled it past
        # half a second), while its faults are injected and reported at once.
        "timing": {"advance": 1.5 * rate, "initialize_fast": 1.5 * rate, "hang": 2.0 * rate},
        "supervision": {"tpdo_timeout_cycles": max(5, round(1.5 * rate)),
                        "heartbeat_timeout_factor": 15.0, "consumer_factor": 15.0},
        "drives": [{"name": name, "node_id": i % per_bus // axes + first_node, **DRIVE,
                    "modes": modes, **({"axis": i % per_bus % axes + 1} if axes > 1 else {}),
                    **({"bus": f"bus{i // per_bus}"} if buses > 1 else {}), **drive}
                   for i, name in enumerate(joints)],
        "controllers": [
            {"name": "pd", "plugin": "pd", "emergency": emergency["name"],
             "params": {"mode": "CSP", "target": 0.3, "velocity_limit": 1.0}},
            {"name": "trajectory", "plugin": "trajectory", "emergency": emergency["name"],
             "params": {"kind": "sine", "amplitude": 0.3, "frequency": 0.5,
                        "blend_time": 0.5, "mode": "CSP"}},
        ],
        "emergency_controllers": [emergency],
        **({"realtime": {"priority": priority}} if priority is not None else {}),
    }


def demo_urdf(joints: list[str]) -> str:
    """The demo's robot for Foxglove's 3D panel: a serial arm of cylinders on a base, one
    revolute joint per drive (named as the drive), about as tall whatever the joint count;
    the joints turn about z and y in turn, so each drive's motion shows."""
    length = min(0.3, 1.2 / len(joints))
    parts = ['<robot name="rocoma_demo_arm">',
             '<material name="grey"><color rgba="0.5 0.5 0.5 1"/></material>',
             '<material name="blue"><color rgba="0.2 0.45 0.9 1"/></material>',
             '<material name="orange"><color rgba="0.95 0.55 0.15 1"/></material>',
             _cylinder_link("base_link", 0.1, 0.05, "grey")]
    parent, z = "base_link", 0.05
    for i, name in enumerate(joints):
        child = f"{name}_link"
        parts += [f'<joint name="{name}" type="revolute"><parent link="{parent}"/>'
                  f'<child link="{child}"/><origin xyz="0 0 {z:g}" rpy="0 0 0"/>'
                  f'<axis xyz="{"0 0 1" if i % 3 == 0 else "0 1 0"}"/>'
                  '<limit lower="-3.1416" upper="3.1416" effort="10" velocity="5"/></joint>',
                  _cylinder_link(child, 0.035, length, ("blue", "orange")[i % 2])]
        parent, z = child, length
    return "\n".join([*parts, "</robot>"])


def _cylinder_link(name: str, radius: float, length: float, material: str) -> str:
    """A link drawn as a cylinder standing on its frame's origin."""
    return (f'<link name="{name}"><visual><origin xyz="0 0 {length / 2:g}"/>'
            f'<geometry><cylinder radius="{radius:g}" length="{length:g}"/></geometry>'
            f'<material name="{material}"/></visual></link>')
