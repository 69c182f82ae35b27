"""Is another manager already driving these buses? Asked before ``run`` writes anything.

Two managers on one bus fight: the second brings up the drives the first has enabled (NMT,
SDO configuration, its own SYNC and RPDOs), and the first falls to FAILPROOF with a cause
that points at the drives, not at the second manager. So a Runtime first listens on each of
its buses, sending nothing, for what a running manager of this config would send there:

- SYNC (0x080): a manager's loop sends one every cycle, on every bus;
- the heartbeat of this manager's node id (0x700 + id, every bus) and its node's state frame
  (0x180 + id, its node's bus): a manager with the same node id, or any node holding it;
- an RPDO to one of this config's drives: another master commanding them.

It listens ``listen_time`` (LISTEN_PERIODS of the longest period those frames come at: the
manager heartbeat's, or the loop's own period at a rate below 10 Hz), on every bus at
once, and names everything it heard. ``rocoma-can run`` refuses in one line when it heard
anything; ``rocoma-can doctor CONFIG`` runs the same listening as a check, and
``check-config`` says what run will listen for. Heard here: a frame on one of those
identifiers, 11-bit, not an error frame. A manager whose loop is stalled for the whole
window, or one on a bus the listening handle cannot see (another interface), is not heard.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import can

from ..drivers.link.bus import open_bus
from ..drivers.plan.config import BusConfig, DriveConfig
from ..drivers.plan.pdo_layout import DriveLayout
from ..drivers.protocol.cia301 import HEARTBEAT, SYNC, TPDO_BASE
from ..errors import BusTaken
from .config import RuntimeConfig
from .host import Check

#: the window, in periods of the slowest frame a running manager sends every period: each
#: is heard at least twice, whatever its phase
LISTEN_PERIODS = 2.5


@dataclass(frozen=True, order=True)
class HeardFrame:
    """A frame heard on one bus: its identifier, and what a frame there means."""
    bus: str     # the bus's label
    cob_id: int
    what: str    # "SYNC (0x080)"


def listen_time(config: RuntimeConfig) -> float:
    """How long to listen (see module): LISTEN_PERIODS x the manager heartbeat's period or
    the loop's, whichever is longer."""
    return LISTEN_PERIODS * max(config.manager.heartbeat_ms / 1000.0, config.dt)


def watched(config: RuntimeConfig, layouts: Sequence[DriveLayout] | None = None
            ) -> dict[str, dict[int, str]]:
    """Per bus label: the identifiers listened for, each with what a frame there means.
    ``layouts``: the drives' PDO layouts, in config order (None: the config's plans)."""
    node = config.manager.node_id
    if layouts is None:
        layouts = [config.plans[d.name].layout for d in config.drives if d.name in config.plans]
        drives: Sequence[DriveConfig] = [d for d in config.drives if d.name in config.plans]
    else:
        drives = config.drives
    first = config.buses[0].label
    ids: dict[str, dict[int, str]] = {}
    for bus in config.buses:
        on = ids[bus.label] = {
            SYNC: f"SYNC (0x{SYNC:03X})",
            HEARTBEAT + node: f"the heartbeat of node {node} (0x{HEARTBEAT + node:03X}), "
                              "this manager's node id"}
        if bus.label == config.node_bus.label:
            state = TPDO_BASE[0] + node
            on[state] = f"the state frame of manager node {node} (0x{state:03X})"
    for drive, layout in zip(drives, layouts):
        on = ids[drive.bus or first]
        said = ", ".join(f"0x{pdo.cob_id:03X}" for pdo in layout.rpdos)
        for pdo in layout.rpdos:
            on.setdefault(pdo.cob_id, f"an RPDO to drive {drive.name!r} ({said})")
    return ids


Opener = Callable[[BusConfig], can.BusABC]


def _open(bus: BusConfig) -> can.BusABC:
    extra: dict[str, object] = {"fd": True} if bus.fd else {}
    if bus.data_bitrate is not None:
        extra["data_bitrate"] = bus.data_bitrate
    return open_bus(bus.interface, bus.channel, bus.bitrate, receive_own_messages=False,
                    **extra)


def listen(config: RuntimeConfig, layouts: Sequence[DriveLayout] | None = None,
           seconds: float | None = None, opener: Opener = _open) -> list[HeardFrame]:
    """Listen on every bus at once for ``seconds`` (``listen_time``), sending nothing;
    what was heard, in the order first heard per bus. OSError: a bus that cannot be
    opened (the one line open_bus gives)."""
    seconds = listen_time(config) if seconds is None else seconds
    ids = watched(config, layouts)
    rank = {b.label: k for k, b in enumerate(config.buses)}
    handles: list[tuple[BusConfig, can.BusABC]] = []
    try:
        for bus in config.buses:
            handles.append((bus, opener(bus)))
        heard: list[list[HeardFrame]] = [[] for _ in handles]
        deadline = time.monotonic() + seconds
        threads = [threading.Thread(target=_listen_one, name="another-manager",
                                    args=(handle, bus.label, ids[bus.label], deadline, out),
                                    daemon=True)
                   for (bus, handle), out in zip(handles, heard)]
        for thread in threads:
            thread.start()
        for thread in threads:  # each ends at the deadline; a stuck recv is left behind
            thread.join(max(0.0, deadline - time.monotonic()) + 1.0)
        # by bus, then SYNC, the manager node's own, the RPDOs (as the identifiers sort)
        return sorted((h for found in heard for h in found),
                      key=lambda h: (rank[h.bus], h.what.startswith("an RPDO"), h.cob_id))
    finally:
        for _, handle in handles:
            handle.shutdown()


def _listen_one(bus: can.BusABC, label: str, ids: dict[int, str], deadline: float,
                out: list[HeardFrame]) -> None:
    try:
        bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids])
    except (can.CanError, NotImplementedError):  # then every frame is read and sorted here
        pass
    seen: set[int] = set()
    while (left := deadline - time.monotonic()) > 0:
        try:
            msg = bus.recv(left)
        except can.CanError:  # a bus that fails while listened to says nothing of managers
            return
        if msg is None or msg.is_extended_id or msg.is_error_frame:
            continue
        what = ids.get(msg.arbitration_id)
        if what is not None and msg.arbitration_id not in seen:
            seen.add(msg.arbitration_id)
            out.append(HeardFrame(label, msg.arbitration_id, what))


def heard_text(config: RuntimeConfig, heard: Sequence[HeardFrame], seconds: float) -> str:
    """What was heard on which bus: "heard within 0.250 s on socketcan:can0: SYNC ..."."""
    channel = {b.label: f"{b.interface}:{b.channel}" for b in config.buses}
    buses: dict[str, list[str]] = {}
    for h in heard:
        said = buses.setdefault(h.bus, [])
        if h.what not in said:
            said.append(h.what)
    return f"heard within {seconds:.3f} s " + "; ".join(
        f"on {channel[label]}: {', '.join(whats)}" for label, whats in buses.items())


def what_to_do(config: RuntimeConfig) -> str:
    node = config.node_bus
    return (f"stop it first (rocoma-can status --interface {node.interface} --channel "
            f"{node.channel} --node {config.manager.node_id} asks it), or give this config a "
            "bus of its own")


def describe_bus_taken(config: RuntimeConfig, heard: Sequence[HeardFrame], seconds: float) -> str:
    """The refusal's one line: what was heard on which bus, and what to do."""
    return (f"another manager is driving the bus: {heard_text(config, heard, seconds)}; "
            f"nothing was sent. {what_to_do(config).capitalize()}")


def doctor_check(config: RuntimeConfig) -> Check:
    """``rocoma-can doctor CONFIG``'s line: the same listening as run's."""
    seconds = listen_time(config)
    try:
        heard = listen(config, seconds=seconds)
    except OSError as exc:  # a link missing or down: its own checks say so
        return Check("another manager", "n/a", f"not listened for: {exc}")
    if heard:
        return Check("another manager", "fail", heard_text(config, heard, seconds),
                     what_to_do(config))
    return Check("another manager", "ok",
                 f"nothing heard in {seconds:.3f} s (no SYNC, no heartbeat of node "
                 f"{config.manager.node_id}, no RPDO to the config's drives)")


def what_run_listens_for(config: RuntimeConfig) -> str:
    """check-config's line: how run tells that another manager drives the bus."""
    ids = watched(config)
    parts = []
    for bus in config.buses:
        rpdos = sorted(i for i, what in ids[bus.label].items() if what.startswith("an RPDO"))
        node = config.manager.node_id
        parts.append(f"{bus.interface}:{bus.channel}: SYNC 0x{SYNC:03X}, node {node}'s "
                     f"heartbeat 0x{HEARTBEAT + node:03X}"
                     + (f", RPDOs {', '.join(f'0x{i:03X}' for i in rpdos)}" if rpdos else ""))
    return (f"before it sends anything, run listens {listen_time(config):.3f} s for another "
            f"manager ({'; '.join(parts)}) and refuses to start if it hears one; "
            "`rocoma-can doctor CONFIG` listens the same way")


def refuse_if_heard(config: RuntimeConfig, layouts: Sequence[DriveLayout] | None = None,
                    seconds: float | None = None) -> None:
    """``listen``, and BusTaken (its one line: ``describe_bus_taken``) when anything was heard."""
    seconds = listen_time(config) if seconds is None else seconds
    heard = listen(config, layouts, seconds)
    if heard:
        raise BusTaken(describe_bus_taken(config, heard, seconds))
