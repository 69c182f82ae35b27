"""Every surface where a stop request reaches the manager from outside, and the one call that
turns "a stop arrived" into the manager's stop.

A surface knows a stop by where it arrives: a COB-ID, an SDO object, a Zenoh key, a
Foxglove service, a command's verb. What the request carries (its payload, its encoding,
its length, the types inside it, whether it is UTF-8 or JSON at all) is never read before
the stop: each surface calls ``StopSurface.stop`` as soon as it knows the request is a stop,
with nothing parsed in front of it, and only then looks at the rest (to answer, to log).
A stop that is refused for what it carries leaves the robot running, which is the one
outcome a stop must never have; a stop from anyone, with anything, is at worst a stopped
robot.

``SURFACES`` is the list, and it is closed: tests/safety/test_every_stop_surface.py drives
every surface here with garbage forms of the request (encodings, empty, oversized, wrong
types, invalid UTF-8, garbage JSON) against a running manager, and fails for a surface
listed here that it has no driver for; it also reads the sources and fails for a call of
the manager's ``emergency_stop``/``failproof_stop`` anywhere but here and the places that
are no request from outside (a fault the hardware found, the loop's own stop, the Zenoh
dead-man, the demo's walk-through). A new surface therefore joins this list, or its tests
fail.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

#: an e-stop (OK -> EMERGENCY where the controller has an emergency controller, else
#: FAILPROOF) or a failproof stop (straight to torque-off)
StopKind = Literal["estop", "failproof"]
KINDS: tuple[StopKind, ...] = ("estop", "failproof")


class Stoppable(Protocol):
    """The manager as a stop sees it (rocoma_can's ControllerManager)."""
    def emergency_stop(self, cause: str = ...) -> None: ...
    def failproof_stop(self, cause: str = ...) -> None: ...


@dataclass(frozen=True)
class StopSurface:
    """One way a stop reaches the manager. ``name``: its key in SURFACES (and the tests');
    ``label``: how the stop's cause names it ("Zenoh e-stop"); ``takes``: what it takes, in
    words (docs/safety.md lists them); ``kinds``: the stops it offers; ``client_of``: a
    surface that calls no manager itself but sends through these (the command line)."""
    name: str
    label: str
    takes: str
    kinds: tuple[StopKind, ...] = KINDS
    client_of: tuple[str, ...] = ()

    def cause(self, kind: StopKind, where: str = "") -> str:
        """The stop's cause as the manager keeps it: "SDO e-stop (0x2110)"."""
        return f"{self.label} {'e-stop' if kind == 'estop' else 'failproof stop'}{where}"

    def stop(self, manager: Stoppable, kind: str, where: str = "") -> None:
        """A stop arrived here: the manager's stop, at once (effective by its next update).
        Any ``kind`` other than "failproof" is an e-stop: a stop never fails for a word."""
        if kind == "failproof":
            manager.failproof_stop(cause=self.cause("failproof", where))
        else:
            manager.emergency_stop(cause=self.cause("estop", where))


CAN_FRAME = StopSurface(
    "can-frame", "CAN",
    "any 11-bit frame on the e-stop COB-ID (manager.estop_cob_id), on any bus of the "
    "manager: data or remote, of any length and content", kinds=("estop",))
SDO = StopSurface(
    "sdo", "SDO",
    "an SDO download to the manager node's 0x2110 (e-stop) or 0x2111 (failproof stop): "
    "expedited, segmented or block, of any size and value; it acts on the request that "
    "opens the transfer")
CLI = StopSurface(
    "cli", "CLI",
    "rocoma-can estop / failproof, over SDO to the node (or --zenoh); any other words on "
    "the command line are ignored, said after the stop is sent", client_of=("sdo", "zenoh"))
ZENOH = StopSurface(
    "zenoh", "Zenoh",
    "a query on <prefix>/estop or <prefix>/failproof, with any payload and encoding")
FOXGLOVE = StopSurface(
    "foxglove", "Foxglove",
    "a call of /rocoma/estop or /rocoma/failproof, with any encoding and payload (the "
    "live view's front hands it to the SDK as an empty JSON call)")

ROS2 = StopSurface(
    "ros2", "ROS 2",
    "a call of the ROS 2 node's std_srvs/srv/Trigger services rocoma/estop or "
    "rocoma/failproof over rmw_zenoh, with any payload, encoding and attachment (none, "
    "garbage, another client's)")

#: every surface (see the module docstring: closed, and tested as a whole)
SURFACES: tuple[StopSurface, ...] = (CAN_FRAME, SDO, CLI, ZENOH, FOXGLOVE, ROS2)
