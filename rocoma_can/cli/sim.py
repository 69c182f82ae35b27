"""``rocoma-can sim``: run a segment of simulated CiA 402 drives on a CAN interface.

Bench testing without hardware: ``rocoma-can sim --channel vcan0 --interface socketcan
--nodes 1-12`` and point the driver (or candump) at vcan0. Faults can be injected at start
or after a delay, e.g. ``--fault 3:0x2310@5`` trips an over-current fault on node 3 five
seconds in. ``--axes 2`` makes every node a two-axis drive (CiA 402-2, a dual-channel
controller: axis 2's objects at +0x800, in the --eds file); --fault trips axis 1, the
other injections are the node's (all its axes).
A status line per axis is printed on SIGUSR1 and every --status-interval s.
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from .args import LONGEST, channel_name, count, positive, seconds, seconds_or_zero
from .exit_codes import FAILED, OK, USAGE

if TYPE_CHECKING:  # imported by run(): `rocoma-can --help` must not import the simulator
    from ..drivers.files.capabilities import DriveCapabilities
    from ..drivers.files.identity import Identity
    from ..drivers.sim.drive import SimulatedDrive
    from ..drivers.sim.segment import SimulatedSegment


def parse_node_ids(text: str) -> list[int]:
    """'1-4,7' -> [1, 2, 3, 4, 7]."""
    ids: list[int] = []
    try:
        for part in text.split(","):
            lo, _, hi = part.strip().partition("-")
            first, last = int(lo), int(hi or lo)
            if not 1 <= first <= last <= 127:  # checked before a range is built
                raise argparse.ArgumentTypeError(f"node ids must be 1..127, got {text!r}")
            ids.extend(range(first, last + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(f"node ids like 1-12 or 1,3,5-7, got {text!r}") from None
    return sorted(set(ids))


@dataclass(frozen=True)
class Injection:
    """One fault flag: NODE[:ARG[:ARG]][@SECONDS]."""
    flag: str
    node: int
    args: tuple[str, ...]
    after: float


def _injection(flag: str, nargs: tuple[int, int]) -> Callable[[str], Injection]:
    def parse(text: str) -> Injection:
        spec, _, after = text.partition("@")
        node, *args = spec.split(":")
        try:
            inj = Injection(flag, int(node), tuple(args), float(after) if after else 0.0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"--{flag}: expected NODE[:ARG][@SECONDS], "
                                             f"got {text!r}") from None
        if not nargs[0] <= len(args) <= nargs[1]:
            raise argparse.ArgumentTypeError(f"--{flag} {text!r}: wrong number of arguments")
        if not 0 <= inj.after <= LONGEST:  # nan would make the timer thread spin
            raise argparse.ArgumentTypeError(
                f"--{flag} {text!r}: @SECONDS must be 0..{LONGEST:.0f}")
        return inj
    return parse


def _int(text: str) -> int:
    return int(text, 0)


#: --identity / --unconfigured keys -> Identity fields
IDENTITY_KEYS = {"vendor": "vendor_id", "product": "product_code", "revision": "revision",
                 "serial": "serial"}


def parse_identity(text: str) -> Identity:
    """'serial=0x1234,vendor=0x9A' -> Identity(serial=0x1234, vendor_id=0x9A)."""
    from ..drivers.files.identity import Identity
    fields: dict[str, int] = {}
    for part in text.split(","):
        key, _, value = part.strip().partition("=")
        if key not in IDENTITY_KEYS:
            raise argparse.ArgumentTypeError(
                f"identity {text!r}: {key!r} is not one of {', '.join(IDENTITY_KEYS)}")
        try:
            fields[IDENTITY_KEYS[key]] = int(value, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"identity {text!r}: {key}: not a number "
                                             f"{value!r}") from None
    try:
        return Identity(**fields)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"identity {text!r}: {exc}") from None


def _node_identity(text: str) -> tuple[int, Identity]:
    node, sep, rest = text.partition(":")
    if not sep or not node.strip().isdigit():
        raise argparse.ArgumentTypeError(f"--identity: expected NODE:KEY=VALUE[,...], "
                                         f"got {text!r}")
    return int(node), parse_identity(rest)


def _unconfigured(text: str) -> Identity:
    identity = parse_identity(text)
    if identity.serial is None:
        raise argparse.ArgumentTypeError(f"--unconfigured {text!r}: give serial= (the "
                                         "node's LSS address tells it from the others)")
    return identity


# flag -> (number of ARGs min/max, help, action on the drive)
INJECTIONS: dict[str, tuple[tuple[int, int], str,
                            Callable[[SimulatedDrive, tuple[str, ...]], Any]]] = {
    "fault": ((0, 1), "NODE[:CODE][@S]: trip a fault (EMCY code, default 0x1000)",
              lambda d, a: d.trip_fault(_int(a[0])) if a else d.trip_fault()),
    "silent": ((0, 0), "NODE[@S]: the drive transmits nothing any more",
               lambda d, a: d.set_silent(True)),
    "no-sync": ((0, 0), "NODE[@S]: the drive stops answering SYNC",
                lambda d, a: d.set_sync_response(False)),
    "tpdo-delay": ((1, 1), "NODE:SECONDS[@S]: send TPDOs late",
                   lambda d, a: d.set_tpdo_delay(float(a[0]))),
    "babble": ((0, 2), "NODE[:COUNT[:COBID]][@S]: flood the bus (default 1000 x 0x001)",
               lambda d, a: d.babble(int(a[0]) if a else 1000,
                                     _int(a[1]) if len(a) > 1 else 0x001)),
    "sto-low": ((0, 0), "NODE[@S]: STO input low", lambda d, a: d.set_sto(True)),
    "position-noise": ((1, 1), "NODE:STD[@S]: noise on 0x6064 (increments)",
                       lambda d, a: d.set_position_noise(float(a[0]))),
}


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "sim", help="run simulated CiA 402 drives on a CAN interface",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--channel", type=channel_name, default="vcan0",
                   help="CAN channel (default vcan0)")
    p.add_argument("--interface", default="socketcan",
                   help="python-can interface: socketcan (default), virtual, ...")
    p.add_argument("--nodes", type=parse_node_ids, default=[1], metavar="IDS",
                   help="node ids, e.g. 1-12 or 1,3,5-7 (default 1)")
    p.add_argument("--eds", default=None, metavar="FILE",
                   help="EDS or DCF the drives emulate: exactly its objects, access types and "
                        "0x6502 modes (default: the shipped generic drive)")
    p.add_argument("--axes", type=count, default=1, metavar="N",
                   help="CiA 402 axes per node, 1..8 (CiA 402-2: axis n's objects at "
                        "index + 0x800 (n - 1); the file must have each axis's 0x6040/0x6041; "
                        "default 1)")
    p.add_argument("--increments-per-rev", type=count, default=1 << 20, metavar="N",
                   help="encoder increments per motor turn where the file has no 0x608F "
                        "(default 1048576)")
    p.add_argument("--rated-torque-nm", type=positive, default=1.0, metavar="NM",
                   help="rated torque where the file has no 0x6076 (default 1.0)")
    p.add_argument("--fd", action="store_true",
                   help="a CAN FD bus: the drives answer in FD frames with bit rate switching "
                        "(on vcan: ip link set vcan0 mtu 72)")
    p.add_argument("--sync-period", type=seconds, default=None, metavar="S",
                   help="integrate each SYNC over this fixed period instead of measured time")
    p.add_argument("--status-interval", type=seconds_or_zero, default=0.0, metavar="S",
                   help="print a status line per axis every S seconds (also on SIGUSR1)")
    p.add_argument("--duration", type=seconds, default=None, metavar="S",
                   help="stop after S seconds (default: run until Ctrl-C / SIGTERM)")
    p.add_argument("--identity", type=_node_identity, action="append", default=[],
                   metavar="NODE:KEY=VALUE[,...]",
                   help="a node's identity object 0x1018, keys vendor, product, revision, "
                        "serial, e.g. 2:vendor=0x9A,serial=0x1234 (default: the file's, "
                        "with a serial number per node: the file's + node id - 1, or the "
                        "node id)")
    p.add_argument("--unconfigured", type=_unconfigured, action="append", default=[],
                   metavar="KEY=VALUE[,...]",
                   help="one more node without a node id (LSS, CiA 305), e.g. serial=0x77: "
                        "it answers only LSS until `rocoma-can lss` gives it one")
    for flag, (nargs, text, _) in INJECTIONS.items():
        p.add_argument(f"--{flag}", type=_injection(flag, nargs), action="append", default=[],
                       metavar="SPEC", help=text)
    p.set_defaults(func=run)


def _inject(segment: SimulatedSegment, inj: Injection) -> None:
    INJECTIONS[inj.flag][2](segment.drives[inj.node], inj.args)
    print(f"sim: node {inj.node}: {inj.flag} {' '.join(inj.args)}".rstrip(), flush=True)


class _Refused(Exception):
    """What ``sim`` refuses before it starts: the line it says and its exit code."""

    def __init__(self, message: str, code: int = USAGE) -> None:
        super().__init__(message)
        self.code = code


def run(args: argparse.Namespace) -> int:
    injections = [inj for flag in INJECTIONS for inj in getattr(args, flag.replace("-", "_"))]
    try:
        caps = _checked(args, injections)
        segment = _opened(args)
    except _Refused as refused:
        print(f"rocoma-can sim: {refused}", file=sys.stderr)
        return refused.code
    if args.eds:  # what the drives are, as a master would find out
        print(f"sim: the drives emulate {caps.source}", flush=True)
        for line in caps.report():
            print(f"sim:   {line}", flush=True)
    _serve(args, segment, injections)
    if segment.errors:
        print(f"rocoma-can sim: the simulation failed: {segment.errors[0]!r}", file=sys.stderr)
        return FAILED
    if segment.bus_errors:  # the drives were cut off meanwhile: say so, and why
        print(f"rocoma-can sim: reading {args.interface} {args.channel} failed "
              f"{segment.bus_errors} time(s) (interface down or gone?); the latest: "
              f"{segment.bus_error}", file=sys.stderr)
        return FAILED
    return OK


def _checked(args: argparse.Namespace, injections: list[Injection]) -> DriveCapabilities:
    """The options checked against each other and the --eds file read (its capabilities);
    _Refused for the first problem."""
    strays = sorted(set(dict(args.identity)) - set(args.nodes))
    if strays:
        raise _Refused(f"--identity: node(s) {strays} not in --nodes")
    for inj in injections:
        if inj.node not in args.nodes:
            raise _Refused(f"--{inj.flag}: node {inj.node} is not in --nodes")
    from ..drivers.link.bus import unknown_interface
    unknown = unknown_interface(args.interface)
    if unknown:
        raise _Refused(f"--interface: {unknown}")
    from ..drivers.files.capabilities import CapabilityError, read_capabilities
    try:
        caps = read_capabilities(args.eds, args.nodes[0])
    except CapabilityError as exc:
        raise _Refused(f"--eds: {exc}") from None
    from ..drivers.sim.objects import axes_problem
    problem = axes_problem(caps.object_dictionary, args.axes)
    if problem:
        raise _Refused(f"--axes {args.axes}: {problem} ({caps.source})")
    return caps


def _opened(args: argparse.Namespace) -> SimulatedSegment:
    """The drives on their bus; _Refused when the options or the bus do not allow them."""
    from ..drivers.sim.lss import IdentityError
    from ..drivers.sim.segment import SimulatedSegment
    try:
        return SimulatedSegment.open(args.channel, args.interface, args.nodes,
                                     eds_path=args.eds, sync_period=args.sync_period,
                                     fd=args.fd, increments_per_rev=args.increments_per_rev,
                                     rated_torque_nm=args.rated_torque_nm,
                                     axes={n: args.axes for n in args.nodes},
                                     identities=dict(args.identity),
                                     unconfigured=args.unconfigured)
    except IdentityError as exc:  # --identity / --unconfigured: the arguments are wrong
        raise _Refused(str(exc)) from None
    except (OSError, ValueError, ImportError) as exc:
        raise _Refused(f"cannot open {args.interface} channel {args.channel}: {exc}",
                       FAILED) from None


def _serve(args: argparse.Namespace, segment: SimulatedSegment,
           injections: list[Injection]) -> None:
    """Run the drives until Ctrl-C, SIGTERM or --duration; a status line per axis on
    SIGUSR1 and every --status-interval. The drives' bus is closed after."""
    # Set by signal handlers, polled below: a handler runs on this (main) thread between two
    # bytecodes and must take no lock (Event.set could wait for ever for the lock that the
    # interrupted Event.wait holds).
    signalled = {"stop": False, "status": False}
    previous: dict[int, Any] = {}

    def on_stop(signum: int, frame: Any) -> None:
        signalled["stop"] = True

    def on_status(signum: int, frame: Any) -> None:
        signalled["status"] = True

    if threading.current_thread() is threading.main_thread():
        for sig, handler in ((signal.SIGTERM, on_stop), (signal.SIGINT, on_stop),
                             (getattr(signal, "SIGUSR1", None), on_status)):
            if sig is not None:
                previous[sig] = signal.signal(sig, handler)
    try:
        with segment:
            _say_started(args, segment)
            _run_until_stopped(args, segment, injections, signalled)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _say_started(args: argparse.Namespace, segment: SimulatedSegment) -> None:
    axes = f" of {args.axes} axes" if args.axes > 1 else ""
    blank = (f" and {len(args.unconfigured)} without a node id (LSS)"
             if args.unconfigured else "")
    print(f"sim: {len(segment.drives)} drive(s){axes} {args.nodes[0]}..{args.nodes[-1]}"
          f"{blank} on {args.interface} {args.channel}"
          f"{' (CAN FD)' if args.fd else ''}; Ctrl-C to stop", file=sys.stderr,
          flush=True)


def _run_until_stopped(args: argparse.Namespace, segment: SimulatedSegment,
                       injections: list[Injection], signalled: dict[str, bool]) -> None:
    start = segment.clock()
    for inj in injections:
        segment.schedule(start + inj.after, _inject, segment, inj)
    interval = args.status_interval if args.status_interval > 0 else None
    next_status = start + interval if interval else None
    end = start + args.duration if args.duration is not None else None
    while not signalled["stop"]:
        now = segment.clock()
        if end is not None and now >= end:
            break
        if signalled["status"] or (next_status is not None and now >= next_status):
            signalled["status"] = False
            print("\n".join(segment.status_lines()), flush=True)
            if next_status is not None:
                next_status = max(next_status + interval, now)
        waits = [t - now for t in (end, next_status) if t is not None]
        time.sleep(min(waits + [0.2]))  # bounded: a signal is seen within 0.2 s
