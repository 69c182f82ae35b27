"""Sub-commands ``scan`` (which nodes are on a bus, and what each one is) and ``lss`` (give
a node a node id by LSS, CiA 305).

``scan`` only reads (SDO uploads; with ``--lss`` also LSS fastscan, which changes no node
id): it may run beside a manager. Exit codes: 0 the scan ran (also when no node
answered), 1 ``lss`` got no answer, a refusal or a malformed answer, or found the node id
taken by a node already on the bus (nothing assigned), and ``scan --lss`` a malformed LSS
answer, 2 usage errors and a bus that cannot be opened or sent on (a link down; a transmit
queue that stays full: no node acknowledges).
"""
from __future__ import annotations

import argparse
import errno
import json
from collections.abc import Callable
from typing import TYPE_CHECKING

from ..errors import LssFailed
from .args import channel_name, node_id, seconds
from .console import err
from .exit_codes import FAILED, OK, USAGE
from .hints import no_socketcan_hint

if TYPE_CHECKING:  # imported when a verb runs: `rocoma-can --help` stays fast
    import can

    from ..drivers.commission.scan import FoundNode
    from ..drivers.files.identity import Identity

#: what a scan that found nothing asks a person to look at
NOTHING_FOUND = ("no nodes answered: check the bit rate (every node's and the interface's "
                 "must be the same), termination (120 ohm at both ends of the bus) and that "
                 "the drives have power")



def on_bus(args: argparse.Namespace, work: Callable[[can.BusABC], int]) -> int:
    """``work`` on a bus opened from --interface/--channel; one line (exit 2) when it cannot
    open, when its link is down, or when sending fails (nothing acknowledges the frames)."""
    import can

    from ..drivers.link import bus as bus_module
    down = _link_down(args.interface, args.channel)
    if down:
        err(down)
        return USAGE
    try:
        bus = bus_module.open_bus(args.interface, args.channel, receive_own_messages=False)
    except OSError as exc:
        err(str(exc) + no_socketcan_hint(exc))
        return USAGE
    try:
        return work(bus)
    except can.CanError as exc:  # SocketCAN: ENOBUFS, ENETDOWN (python-can's error_code)
        err(f"{args.interface}:{args.channel}: {exc}"
            + _send_failure_hint(getattr(exc, "error_code", None), args.channel))
        return USAGE
    finally:
        bus.shutdown()


def _link_down(interface: str, channel: str) -> str | None:
    """The one line for a SocketCAN link that is down or missing (as doctor says it, and
    before python-can logs one of its own), else None."""
    if interface != "socketcan" or not channel or "/" in channel or channel.startswith("."):
        return None
    from ..drivers.link.can_link import LinkReading, from_sysfs, socketcan_in_kernel
    link = from_sysfs(channel)
    if link is None and not socketcan_in_kernel():
        return None  # open_bus says so, with what to do instead
    if link is None or not link.is_can:  # missing, or eth0, lo: as doctor says it
        from ..runtime.can_checks import Wanted, link_checks
        exists = link_checks(LinkReading(channel, link), Wanted(channel))[0]
        return f"{interface}:{channel}: {exists.found}: {exists.fix}"
    if link.up:
        return None
    return f"{interface}:{channel}: the link is down" + _send_failure_hint(errno.ENETDOWN,
                                                                           channel)


def _send_failure_hint(code: int | None, channel: str) -> str:
    if code == errno.ENETDOWN:
        return (f": sudo ip link set {channel} up (at the drives' bit rate: rocoma-can doctor "
                "checks the link)")
    if code in (errno.ENOBUFS, errno.EAGAIN):
        return ("; the transmit queue stays full: no node acknowledges the frames: "
                + NOTHING_FOUND.split(": ", 1)[1])
    return ""


def _hex(value: int | None, digits: int = 8) -> str:
    return "-" if value is None else f"0x{value:0{digits}X}"


def _period(ms: int | None) -> str:
    return "-" if ms is None else f"{ms} ms" if ms else "off"


#: the row of a node id more than one device answers at: its cells would mix them
SEVERAL = "two or more devices answer here: their answers mix (see below)"


def table(nodes: list[FoundNode]) -> list[str]:
    """One row per node, columns as wide as their widest cell; an object that came
    malformed is "malformed" (not "-", which is an object the node lacks), and a node id
    more than one device answers at says so instead of its cells."""
    from ..drivers.commission.scan import device_type_text
    from ..drivers.files.identity import SUBINDEX
    from ..drivers.protocol.cia301 import DEVICE_TYPE, IDENTITY, PRODUCER_HEARTBEAT_TIME
    head = ("node", "vendor", "product", "revision", "serial", "device type", "name",
            "software", "heartbeat", "NMT state")
    cells: list[tuple[str, ...]] = []
    for n in nodes:
        def shown(index: int, subindex: int, text: str, node: FoundNode = n) -> str:
            return "malformed" if f"0x{index:04X}:{subindex}" in node.malformed else text
        ident = n.identity
        cells.append((
            str(n.node_id),
            *(shown(IDENTITY, SUBINDEX[k], _hex(getattr(ident, k))) for k in SUBINDEX),
            shown(DEVICE_TYPE, 0, device_type_text(n.device_type)),
            n.device_name or "-", n.software_version or "-",
            shown(PRODUCER_HEARTBEAT_TIME, 0, _period(n.heartbeat_ms)), n.nmt_state))
    rows = [head] + [c for c, n in zip(cells, nodes) if not n.several_devices]
    widths = [max(len(row[k]) for row in rows) for k in range(len(head))]
    widths[0] = max([widths[0]] + [len(c[0]) for c in cells])
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip()
             for row in [head]]
    for row, n in zip(cells, nodes):
        text = (row[0].ljust(widths[0]) + "  " + SEVERAL) if n.several_devices else \
            "  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip()
        lines.append(text)
    lines += [f"node {n.node_id}: {n.problem}" for n in nodes if n.problem]
    return lines


def _scan(args: argparse.Namespace) -> int:
    from ..drivers.commission.scan import scan

    def work(bus: can.BusABC) -> int:
        nodes = scan(bus, timeout=args.timeout, listen=args.listen)
        try:
            unconfigured = _unconfigured(bus, args.timeout) if args.lss else None
        except LssFailed as exc:  # the nodes found are still worth their lines
            if not args.json and nodes:
                print("\n".join(table(nodes)), flush=True)
            err(f"scan --lss: {exc}")
            return FAILED
        if args.json:
            print(json.dumps({"nodes": [n.as_json() for n in nodes],
                              **({"unconfigured": [vars(i) for i in unconfigured]}
                                 if unconfigured is not None else {})}, indent=2))
            return OK
        if nodes:
            print("\n".join(table(nodes)), flush=True)
        if unconfigured:
            print(f"{len(unconfigured)} node(s) without a node id (LSS; give one with "
                  "`rocoma-can lss`):")
            for identity in unconfigured:
                print(f"  {identity.describe()}")
        if not nodes and not unconfigured:
            print(NOTHING_FOUND, flush=True)
        return OK
    return on_bus(args, work)


def _unconfigured(bus: can.BusABC, timeout: float) -> list[Identity]:
    from ..drivers.commission.lss import find_unconfigured
    from ..drivers.link.bus import CanopenBus
    lent = CanopenBus(bus)
    try:
        return find_unconfigured(lent.network, timeout=min(timeout, 1.0))
    finally:
        lent.close()


def _lss(args: argparse.Namespace) -> int:
    from ..drivers.commission.lss import assign, bit_timing_index
    from ..drivers.commission.scan import TIMEOUT as SDO_TIMEOUT
    from ..drivers.commission.scan import present
    from ..drivers.files.identity import Identity
    from ..drivers.link.bus import CanopenBus
    address = None
    if not args.fastscan:
        parts = {"vendor_id": args.vendor, "product_code": args.product,
                 "revision": args.revision, "serial": args.serial}
        missing = [f"--{k}" for k, v in zip(("vendor", "product", "revision", "serial"),
                                             parts.values()) if v is None]
        if missing:
            err(f"lss: an LSS address needs {', '.join(missing)} too (or --fastscan)")
            return USAGE
        address = Identity(**parts)
    if args.bitrate is not None:
        try:
            bit_timing_index(args.bitrate)
        except ValueError as exc:
            err(f"lss: --bitrate: {exc}")
            return USAGE

    def work(bus: can.BusABC) -> int:
        lent = CanopenBus(bus)
        try:
            target = assign(lent.network, args.set_node_id, address, bitrate=args.bitrate,
                            store=args.store, timeout=args.timeout,
                            occupant=lambda n: present(lent.network, n, listen=args.listen,
                                                       timeout=max(args.timeout, SDO_TIMEOUT)))
        except LssFailed as exc:
            err(str(exc))
            return FAILED
        finally:
            lent.close()
        rate = f", bit rate {args.bitrate} (from its next power-up)" if args.bitrate else ""
        kept = "stored" if args.store else "not stored: lost at power-off (--store keeps it)"
        print(f"{target.describe()}: node id {args.set_node_id}{rate}, {kept}; a node "
              "that had no node id starts with it now, one that had one at its next NMT "
              "reset", flush=True)
        return OK
    return on_bus(args, work)


def _u32(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        value = -1
    if not 0 <= value <= 0xFFFF_FFFF:
        raise argparse.ArgumentTypeError(f"expected an unsigned 32-bit number, got {text!r}")
    return value


def bus_options(p: argparse.ArgumentParser, timeout: float, what: str) -> None:
    p.add_argument("--channel", type=channel_name, required=True, help="CAN channel, e.g. can0")
    p.add_argument("--interface", default="socketcan",
                   help="python-can interface (default socketcan)")
    p.add_argument("--timeout", type=seconds, default=timeout, metavar="S",
                   help=f"{what} (default {timeout:g})")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from ..drivers.commission.scan import LISTEN, TIMEOUT  # constants only: no canopen import
    p = subparsers.add_parser(
        "scan", help="list the nodes on a bus: identity, device type, name, NMT state",
        description="Listen for heartbeats, probe node ids 1..127 by SDO, and read each "
                    "node's 0x1000, 0x1018, 0x1008, 0x100A and 0x1017. Reads only: it may "
                    "run beside a manager.")
    bus_options(p, TIMEOUT, "seconds to wait for each SDO answer")
    p.add_argument("--listen", type=seconds, default=LISTEN, metavar="S",
                   help=f"listen for heartbeats this long first (default {LISTEN:g})")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--lss", action="store_true",
                   help="also list nodes without a node id (LSS fastscan, CiA 305)")
    p.set_defaults(func=_scan)

    from ..drivers.commission.lss import TIMEOUT as LSS_TIMEOUT
    p = subparsers.add_parser(
        "lss", help="give a node a node id (and bit rate) by LSS (CiA 305)",
        description="Select one node by its LSS address (0x1018: --vendor --product "
                    "--revision --serial) or the first unconfigured one LSS fastscan "
                    "finds, and give it --set-node-id (and --bitrate); --store keeps "
                    "them across a power cycle.")
    bus_options(p, LSS_TIMEOUT, "seconds to wait for each LSS answer")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--serial", type=_u32, help="serial number (0x1018:4)")
    which.add_argument("--fastscan", action="store_true",
                       help="the first node without a node id that LSS fastscan finds")
    for flag, sub in (("vendor", 1), ("product", 2), ("revision", 3)):
        p.add_argument(f"--{flag}", type=_u32, help=f"0x1018:{sub} (with --serial)")
    p.add_argument("--set-node-id", type=node_id, required=True, metavar="ID",
                   help="the node id to give, 1..127")
    p.add_argument("--bitrate", type=int, default=None, metavar="B",
                   help="also the bit rate, bit/s (CiA 305 table: 1000000 ... 10000)")
    p.add_argument("--store", action="store_true",
                   help="store the configuration in the node (kept across a power cycle)")
    p.add_argument("--listen", type=seconds, default=LISTEN, metavar="S",
                   help="first listen this long for a node already at --set-node-id (its "
                        f"heartbeat; then an SDO probe); default {LISTEN:g}")
    p.set_defaults(func=_lss)


__all__ = ["register", "table", "NOTHING_FOUND"]
