"""SocketCAN links judged against the buses of a configuration (``rocoma-can doctor``).

A link that is missing, down, at another bit rate than its drives or bus-off stops the
manager from running as configured: FAIL. What only costs robustness is WARN, with the
reason and the command that fixes it:

* txqueuelen below ``TXQUEUELEN_MIN``: one cycle's frames (SYNC, every drive's RPDOs, the
  heartbeat) plus an SDO burst (``status``) must fit the kernel's queue, or a send fails
  with ENOBUFS; ``tpdo_timeout_cycles`` such cycles in a row are a bus fault (an e-stop).
* restart-ms 0: after a bus-off the controller stays off the bus until root restarts it.
  The manager latches a bus-off itself (a failproof stop of every drive on the bus, until
  ``recover``), so an automatic restart resumes no motion; it only lets ``recover`` find
  the bus back without a root shell. ``RESTART_MS`` is long enough that a bus that fails
  again at once (a short, a wrong bit rate) is not retried hundreds of times a second.
* an error state short of bus-off (warning, passive) or error counters above zero: frames
  are being destroyed somewhere (termination, a stub, a node at another bit rate).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from ..drivers.link.can_link import CANFD_MTU, LinkReading
from ..drivers.plan.config import BusConfig
from .config_drives import DEFAULT_BITRATE
from .host import Check, Status

#: the least transmit queue recommended on a real CAN link (SocketCAN's default is 10)
TXQUEUELEN_MIN = 128
#: ms a controller waits before it rejoins the bus after a bus-off
RESTART_MS = 100
HEALTHY = "ERROR-ACTIVE"


@dataclass(frozen=True)
class Wanted:
    """What a link should be. ``bitrate`` None: nothing to compare with (no config);
    ``assumed``: the config gives none and check-config assumed DEFAULT_BITRATE."""
    channel: str
    bitrate: int | None = None
    assumed: bool = False
    fd: bool | None = None
    data_bitrate: int | None = None

    @classmethod
    def of(cls, bus: BusConfig) -> Wanted:
        data = (bus.data_bitrate or bus.bitrate or DEFAULT_BITRATE) if bus.fd else None
        return cls(bus.channel, bus.bitrate or DEFAULT_BITRATE, bus.bitrate is None, bus.fd,
                   data)


def setup_command(name: str, bitrate: int, data_bitrate: int | None = None) -> str:
    """The commands that bring a CAN controller up as wanted, down first (bit timing can
    only be set on a link that is down)."""
    fd = f" dbitrate {data_bitrate} fd on" if data_bitrate else ""
    return (f"sudo ip link set {name} down && sudo ip link set {name} type can bitrate "
            f"{bitrate}{fd} restart-ms {RESTART_MS} && sudo ip link set {name} up")


def _missing(want: Wanted) -> Check:
    name = want.channel
    if name.startswith("vcan"):
        fix = (f"sudo modprobe vcan && sudo ip link add dev {name} type vcan && "
               f"sudo ip link set {name} up")
    else:
        fix = ("connect the adapter or load its driver (dmesg | grep -i can; "
               "ip -br link lists the links there are), or correct the channel in the config")
    return Check(f"{name}: exists", "fail", f"no network interface {name!r}", fix)


def link_checks(reading: LinkReading, want: Wanted) -> list[Check]:
    """The checklist of one link, in the order a person fixes it."""
    name = want.channel
    link = reading.link
    if link is None:
        return [_missing(want)]
    if not link.is_can:  # eth0, lo: up, no bit rate to compare; nothing else applies
        return [Check(f"{name}: exists", "fail", f"link/{link.link_type}, not a CAN link: "
                      "no CAN frame can be sent or received on it",
                      "name a CAN interface in the config or --channel (ip link shows "
                      "every link; CAN ones say link/can)")]
    kind = link.kind or "unknown (iproute2's details missing)"
    checks = [Check(f"{name}: exists", "ok", f"{kind} link, mtu {link.mtu}")]
    is_can = link.kind == "can"
    bitrate = want.bitrate or link.bitrate or DEFAULT_BITRATE
    data_bitrate = want.data_bitrate if want.fd else (link.data_bitrate if link.fd else None)
    setup = setup_command(name, bitrate, data_bitrate)
    if link.up:
        checks.append(Check(f"{name}: up", "ok", f"up (operstate {link.operstate})"))
    else:
        fix = setup if is_can else f"sudo ip link set {name} up"
        checks.append(Check(f"{name}: up", "fail", "down: no frame can be sent or received",
                            fix))
    if reading.unread:
        status: Status = "warn" if want.bitrate else "n/a"
        checks.append(Check(f"{name}: bit rate, state, counters", status,
                            f"not judged: {reading.unread}", reading.fix))
        return checks
    if not is_can:
        return [*checks, *_virtual_checks(name, link.kind, link.mtu, want)]
    checks.append(_bitrate_check(name, link.bitrate, want, setup))
    checks.append(_fd_check(name, link.fd, link.data_bitrate, want, setup))
    checks.append(_state_check(name, link.up, link.state))
    checks.append(_counters_check(name, link.berr, link.counters))
    queue = link.txqueuelen
    if queue is not None and queue < TXQUEUELEN_MIN:
        checks.append(Check(f"{name}: txqueuelen", "warn",
                            f"{queue}: a burst of frames (a cycle's PDOs and an SDO answer) "
                            "can fill it, and a full queue fails sends with ENOBUFS",
                            f"sudo ip link set {name} txqueuelen {TXQUEUELEN_MIN}"))
    else:
        checks.append(Check(f"{name}: txqueuelen", "ok", f"{queue}"))
    if link.restart_ms == 0:
        checks.append(Check(f"{name}: restart-ms", "warn",
                            "0: after a bus-off the link stays off the bus until root "
                            "restarts it (the manager latches a bus-off either way)", setup))
    else:
        checks.append(Check(f"{name}: restart-ms", "ok", f"{link.restart_ms} ms"))
    return checks


def _virtual_checks(name: str, kind: str | None, mtu: int, want: Wanted) -> list[Check]:
    """vcan and vxcan: no controller, so no bit rate, state, queue or restart; FD is the MTU."""
    found = f"{kind}: virtual, frames are delivered at once"
    checks = [Check(f"{name}: bit rate", "n/a", f"{kind} has no bit rate (the config's is for "
                    "a real bus)" if want.bitrate else f"{kind} has no bit rate"),
              Check(f"{name}: state", "n/a", f"{found}, no controller state")]
    if want.fd:
        if mtu == CANFD_MTU:
            checks.append(Check(f"{name}: CAN FD", "ok", f"mtu {mtu}: FD frames pass"))
        else:
            checks.append(Check(f"{name}: CAN FD", "fail",
                                f"mtu {mtu}: FD frames are refused (fd: true needs mtu "
                                f"{CANFD_MTU})", f"sudo ip link set {name} down && sudo ip "
                                f"link set {name} mtu {CANFD_MTU} && sudo ip link set {name} "
                                "up"))
    return checks


def _bitrate_check(name: str, actual: int | None, want: Wanted, setup: str) -> Check:
    check = f"{name}: bit rate"
    if not actual:
        return Check(check, "fail", "no bit rate set on the controller", setup)
    if want.bitrate is None:
        return Check(check, "n/a", f"{actual} bit/s (no config to compare with)")
    if actual == want.bitrate:
        return Check(check, "ok", f"{actual} bit/s")
    if want.assumed:
        return Check(check, "warn", f"{actual} bit/s; the config gives no bitrate and its bus "
                     f"load was judged at {want.bitrate}", f"bitrate: {actual} in the config's "
                     "bus")
    return Check(check, "fail", f"{actual} bit/s, the config says {want.bitrate}: no frame "
                 "would be understood", setup)


def _fd_check(name: str, fd: bool, actual: int | None, want: Wanted, setup: str) -> Check:
    check = f"{name}: CAN FD"
    if not want.fd:
        mode = f"FD on (data phase {actual} bit/s)" if fd else "classic CAN"
        judged = "the config sends classic frames" if want.fd is False else "no config"
        return Check(check, "n/a", f"{mode}; {judged}")
    if not fd:
        return Check(check, "fail", "FD is off: the config's FD frames would be refused", setup)
    if actual != want.data_bitrate:
        return Check(check, "fail", f"data phase {actual} bit/s, the config says "
                     f"{want.data_bitrate}", setup)
    return Check(check, "ok", f"FD on, data phase {actual} bit/s")


def _state_check(name: str, up: bool, state: str | None) -> Check:
    check = f"{name}: controller state"
    if state is None:
        return Check(check, "n/a", "the driver reports no state")
    if not up:
        return Check(check, "n/a", f"{state} (the link is down)")
    if state == HEALTHY:
        return Check(check, "ok", state)
    if state == "BUS-OFF":
        return Check(check, "fail", "BUS-OFF: the controller has left the bus after too many "
                     "errors", "check wiring, termination (60 Ω between CAN_H and CAN_L, power "
                     "off) and every node's bit rate, then "
                     f"sudo ip link set {name} type can restart")
    return Check(check, "warn", f"{state}: frames are being destroyed on this bus",
                 "check wiring, termination and every node's bit rate (candump -e "
                 f"{name},0~0,#FFFFFFFF shows the error frames)")


def _counters_check(name: str, berr: tuple[int, int] | None,
                    counters: Mapping[str, int]) -> Check:
    check = f"{name}: error counters"
    parts = [f"tx {berr[0]}, rx {berr[1]}"] if berr else ["tx/rx not reported by the driver"]
    nonzero = {k: v for k, v in counters.items() if v}
    if berr and (berr[0] or berr[1]) or nonzero:
        parts += [f"{k.replace('_', ' ')} {v}" for k, v in sorted(nonzero.items())]
        return Check(check, "warn", "; ".join(parts),
                     "errors since the link came up: check wiring and termination; the "
                     "counts restart when the link goes down and up")
    return Check(check, "ok", "; ".join([*parts, "no errors, drops or bus-offs counted"]))
