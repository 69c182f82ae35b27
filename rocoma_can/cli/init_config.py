"""``rocoma-can init-config``: a run config from what a scan found on the bus.

Each node the scan found is matched to a device file in ``--eds-dir`` by the vendor-ID and
product code its identity object (0x1018) reports and the file's [DeviceInfo] gives (a
matching revision, then a DCF commissioned for that node id, win among several). A matched
CiA 402 drive becomes a drive entry fitted to its file the way the demo fits one (the modes
it can run, its scaling, every axis of a multi-axis device) and carries the identity it was
seen with, so bring-up refuses a drive that is not this one (swapped node ids or cables).
The rest are comments: nodes no file matches, devices that are not drives, drives the
manager could not supervise (they would keep running when the manager dies: left out
until someone decides so, in writing). The rate is the highest of 1000, 500, 250, 100 Hz
whose worst-case bus load fits. The output is checked like any config before it is
written: what check-config refuses is never written.

Safe defaults throughout: the manager starts latched (``estop_must_be_cleared``), the one
controller holds the pose it finds (pd without a target), joint names say they are
placeholders, and limits are left for a person to fill in.
"""
from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from ..exit_codes import FAILED, OK, USAGE
from .scan import bus_options, on_bus

#: rates tried, highest first
RATES = (1000, 500, 250, 100)
#: CiA 402 in the low 16 bits of the device type (0x1000)
CIA402 = 402
MANAGER_NODE_IDS = (100, 127, 126, 125)
SUFFIXES = (".eds", ".dcf")


class Found(Protocol):
    """What init-config needs of a node a scan found (drivers.scan.FoundNode)."""
    @property
    def node_id(self) -> int: ...
    @property
    def identity(self) -> Any: ...  # drivers.identity.Identity
    @property
    def device_type(self) -> int | None: ...


@dataclass(frozen=True)
class DeviceFileInfo:
    """One file of the directory, by what it says it is for."""
    path: str
    vendor: int | None
    product: int | None
    revision: int | None
    node_id: int | None  # a DCF's commissioned node id


def index_device_files(directory: str) -> tuple[list[DeviceFileInfo], list[str]]:
    """Every EDS/DCF in ``directory`` (not below it) and a note per file it cannot read."""
    from ..drivers.device_file import DeviceFileError, read_device_file
    files, notes = [], []
    for entry in sorted(os.scandir(directory), key=lambda e: e.name):
        if not entry.name.lower().endswith(SUFFIXES):
            continue
        try:
            if not entry.is_file():
                continue
        except OSError as exc:  # a symbolic link in a loop, say
            notes.append(f"{entry.name}: not read ({exc.strerror or exc})")
            continue
        try:
            device = read_device_file(entry.path)
        except DeviceFileError as exc:
            notes.append(f"{entry.name}: not read ({exc})")
            continue
        info = {k.lower(): v for k, v in device.sections.get("DeviceInfo", {}).items()}
        files.append(DeviceFileInfo(entry.path, _number(info.get("vendornumber")),
                                    _number(info.get("productnumber")),
                                    _number(info.get("revisionnumber")),
                                    device.commissioned_node_id))
    return files, notes


def _number(text: str | None) -> int | None:
    if not text:
        return None
    try:
        return int(text.strip(), 0)
    except ValueError:
        return None


def match(node_id: int, identity: Any, files: Sequence[DeviceFileInfo]) -> list[DeviceFileInfo]:
    """The files made for this device, best first: same vendor and product (a file that
    names no vendor matches nothing), then same revision, then commissioned for this node."""
    same = [f for f in files if f.vendor and f.vendor == identity.vendor_id
            and f.product == identity.product_code]
    return sorted(same, key=lambda f: (f.revision != identity.revision,
                                       f.node_id not in (None, node_id), f.node_id is None,
                                       f.path))


def _hex(value: int | None) -> str:
    return "null" if value is None else f"0x{value:08X}"


def _identity_yaml(identity: Any) -> str:
    fields = [(k, getattr(identity, k)) for k in ("vendor_id", "product_code", "revision",
                                                  "serial")]
    return "{" + ", ".join(f"{k}: 0x{v:X}" for k, v in fields if v is not None) + "}"


def _flow(mapping: dict[str, Any]) -> str:
    """A YAML flow mapping of plain scalars and lists (what a drive entry holds)."""
    import yaml
    return yaml.safe_dump(mapping, default_flow_style=True, sort_keys=False,
                          width=10_000).strip()


class NothingToConfigure(ValueError):
    """No drive could be configured (the message says why, per node); ``notes``: the files
    of the folder that could not be read."""

    def __init__(self, message: str, notes: list[str]) -> None:
        super().__init__(message)
        self.notes = notes


@dataclass
class Generated:
    text: str
    drives: int
    notes: list[str]


def generate(found: Sequence[Found], eds_dir: str, interface: str, channel: str,
             bitrate: int, base: str = ".") -> Generated:
    """The commented YAML for ``found`` (device file paths relative to ``base``, the
    directory the YAML will be in); NothingToConfigure (a ValueError) when no drive could
    be configured."""
    from .demo_config import emulate
    files, notes = index_device_files(eds_dir)
    taken = {n.node_id for n in found}
    manager_id = next((i for i in MANAGER_NODE_IDS if i not in taken), None)
    if manager_id is None:
        manager_id = next(i for i in range(127, 0, -1) if i not in taken)
    drives: list[dict[str, Any]] = []
    lines: list[str] = []   # the drives section, entries and comments in node order
    modes_all: set[str] = set()
    for node in sorted(found, key=lambda n: n.node_id):
        ident = node.identity
        seen = f"node {node.node_id}: {ident.describe()}"
        if node.device_type is not None and node.device_type & 0xFFFF != CIA402:
            lines.append(f"  # {seen}: device type 0x{node.device_type:08X}, not a CiA 402 "
                         "drive: not configured")
            continue
        candidates = match(node.node_id, ident, files)
        if not candidates:
            lines.append(f"  # {seen}: no file in {eds_dir} is for vendor "
                         f"{_hex(ident.vendor_id)} product {_hex(ident.product_code)}: add "
                         "its EDS/DCF and run init-config again")
            continue
        chosen = candidates[0]
        try:
            fitted = emulate(chosen.path, 1)
        except ValueError as exc:
            lines.append(f"  # {seen}: {Path(chosen.path).name}: {exc}")
            continue
        others = ", ".join(Path(f.path).name for f in candidates[1:])
        guessed = _guessed(chosen.path)
        drive = dict(fitted.drive)
        unsupervised = drive.pop("accept_unsupervised", False)
        lines.append(f"  # node {node.node_id}: {Path(chosen.path).name}"
                     + (f" (also matching: {others})" if others else "")
                     + f"; modes {', '.join(fitted.modes)}"
                     + (f"; {' and '.join(guessed)} not in its file: a guess, take it "
                        "from the datasheet" if guessed else ""))
        for axis in range(1, fitted.axes + 1):
            entry: dict[str, Any] = {"name": f"node{node.node_id}"
                                     + (f"_axis{axis}" if fitted.axes > 1 else ""),
                                     "node_id": node.node_id}
            if axis > 1:
                entry["axis"] = axis
            entry.update(drive)
            entry["eds"] = chosen.path
            entry["modes"] = list(fitted.modes)
            if unsupervised:
                lines.append("  # NOT CONFIGURED: its file gives no way to make the drive "
                             "let go of a lost manager (no heartbeat consumer with 0x6007 "
                             "or 0x1029, no life guarding): it would keep running when the "
                             "manager dies. Read docs/safety.md; to run it anyway, uncomment "
                             "and add accept_unsupervised: true")
                lines.append(f"  # - {_flow({**entry, 'eds': os.path.relpath(chosen.path, base)})}")
                continue
            text = _flow({**entry, "eds": os.path.relpath(chosen.path, base)})[:-1] \
                + f", identity: {_identity_yaml(ident)}}}"
            lines.append(f"  - {text}   # rename: which joint is this?")
            drives.append(entry)
            modes_all.update(fitted.modes)
    if not drives:
        raise NothingToConfigure("no drive could be configured: " + ("; ".join(
            line.strip().lstrip("# ") for line in lines) or "the scan found no node"), notes)
    damp = all("cst" in d["modes"] for d in drives)
    emergency = ("{name: stop, plugin: damp, params: {damping: 0.05, still_time: 0.2, "
                 "timeout: 2.0}}" if damp else "{name: stop, plugin: hold, params: {mode: CSP}}")
    rate = _fitting_rate(drives, interface, bitrate, notes)
    header = [
        "# Generated by rocoma-can init-config from a scan of "
        f"{interface}:{channel}; check every line before the robot moves.",
        "# Drive names are placeholders (rename them to your joints); each drive carries the",
        "# identity it was seen with: bring-up refuses a drive that differs (swapped node ids",
        "# or cables). Joint limits are not known here: add limits per drive (docs).",
        f"bus: {{interface: {interface}, channel: {channel}, bitrate: {bitrate}}}",
        f"rate: {rate}   # the highest of {', '.join(map(str, RATES))} Hz the bus carries "
        "(worst case)",
        f"manager: {{node_id: {manager_id}, heartbeat_ms: 100, estop_must_be_cleared: true}}",
        "# realtime: {priority: 80, cpus: [1]}   # SCHED_FIFO on an isolated CPU: see what",
        "#                                        # `rocoma-can doctor` says of this host",
        "drives:",
    ]
    footer = [
        "controllers:",
        "  # holds the pose it finds on the switch (pd without a target); the drives close",
        "  # the loop (CSP)",
        "  - {name: hold_pose, plugin: pd, params: {mode: CSP, velocity_limit: 0.2}, "
        "emergency: stop}",
        "emergency_controllers:",
        f"  - {emergency}",
    ]
    text = "\n".join(header + lines + footer) + "\n"
    return Generated(text, len(drives), notes)


def _guessed(path: str) -> list[str]:
    """The scaling keys the demo's fit had to guess for this file (no 0x608F / 0x6076)."""
    from ..drivers.capabilities import read_capabilities
    from ..drivers.cia402 import POSITION_ENCODER_RESOLUTION, RATED_TORQUE
    caps = read_capabilities(path, 1)
    return [key for key, ok in (
        ("increments_per_rev", caps.value(POSITION_ENCODER_RESOLUTION, 1)
         and caps.value(POSITION_ENCODER_RESOLUTION, 2)),
        ("rated_torque_nm", caps.value(RATED_TORQUE))) if not ok]


def _fitting_rate(drives: list[dict[str, Any]], interface: str, bitrate: int,
                  notes: list[str]) -> int:
    from ..drivers.config import DriveConfig
    from ..drivers.drive_plan import plan_drives
    from ..runtime.bus_load import bus_load
    if interface == "inproc":
        return RATES[0]
    layouts = [p.layout for p in plan_drives([DriveConfig.from_dict(d) for d in drives])]
    for rate in RATES:
        if bus_load(layouts, float(rate), bitrate).load <= 1.0:
            return rate
    notes.append(f"even {RATES[-1]} Hz overloads a {bitrate:,} bit/s bus: check-config says "
                 "by how much; spread the drives over more buses")
    return RATES[-1]


def _init_config(args: argparse.Namespace) -> int:
    problem = None
    if not os.path.isdir(args.eds_dir):
        problem = f"--eds-dir {args.eds_dir}: not a directory"
    else:
        try:
            os.listdir(args.eds_dir)
        except OSError as exc:
            problem = f"--eds-dir {args.eds_dir}: cannot read ({exc.strerror or exc})"
    if problem is None and args.output:
        why = _not_writable(Path(args.output))
        problem = f"-o {args.output}: {why}" if why else None
    if problem:  # before the scan, which takes seconds
        print(f"rocoma-can: init-config: {problem}", file=sys.stderr)
        return USAGE
    return on_bus(args, lambda bus: _write(args, bus))


def _not_writable(path: Path) -> str | None:
    """Why the config cannot be written to ``path``, or None (it may still fail later)."""
    from ..user_files import kind
    folder = path.parent
    if not folder.is_dir():
        return f"no folder {folder} to write it in"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"the folder {folder} is not writable"
    try:
        what = kind(path.stat().st_mode)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return exc.strerror or str(exc)
    return f"is {what}, not a file to write" if what else None


def _write(args: argparse.Namespace, bus: Any) -> int:
    import yaml

    from ..drivers.scan import scan
    from ..errors import ConfigError
    from ..runtime.config import validate
    found = scan(bus, timeout=args.timeout, listen=args.listen)
    base = Path(args.output).resolve().parent if args.output else Path.cwd()
    try:
        made = generate(found, args.eds_dir, args.interface, args.channel, args.bitrate,
                        str(base))
    except ValueError as exc:
        for note in getattr(exc, "notes", ()):  # files not read: maybe why none matched
            print(f"rocoma-can: init-config: note: {note}", file=sys.stderr)
        print(f"rocoma-can: init-config: {exc}", file=sys.stderr)
        return FAILED
    try:
        validate(yaml.safe_load(made.text), args.output or "<init-config>", base)
    except ConfigError as exc:  # a bug of ours: never hand out a config check-config refuses
        print(f"rocoma-can: init-config: the generated config does not pass its own check: "
              f"{exc}", file=sys.stderr)
        return FAILED
    for note in made.notes:
        print(f"rocoma-can: init-config: note: {note}", file=sys.stderr)
    if args.output:
        try:
            Path(args.output).write_text(made.text, encoding="utf-8")
        except OSError as exc:
            print(f"rocoma-can: init-config: -o {args.output}: cannot write "
                  f"({exc.strerror or exc})", file=sys.stderr)
            return USAGE
        print(f"init-config: {made.drives} drive(s) written to {args.output}; next: "
              f"rocoma-can check-config {args.output}", file=sys.stderr)
    else:
        sys.stdout.write(made.text)
    return OK


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from ..cli_args import count, seconds
    from ..drivers.scan import LISTEN, TIMEOUT  # constants only: no canopen import
    p = subparsers.add_parser(
        "init-config", help="a run config from a scan of the bus and a folder of EDS/DCF files",
        description="Scan the bus (as `rocoma-can scan`), match each node to a file in "
                    "--eds-dir by its vendor-ID and product code, and write a commented "
                    "config that check-config accepts: a drive per matched CiA 402 node with "
                    "the identity it was seen with; the rest as comments.")
    bus_options(p, TIMEOUT, "seconds to wait for each SDO answer")
    p.add_argument("--listen", type=seconds, default=LISTEN, metavar="S",
                   help=f"listen for heartbeats this long first (default {LISTEN:g})")
    p.add_argument("--eds-dir", required=True, metavar="DIR",
                   help="the drives' EDS/DCF files (matched by vendor and product)")
    p.add_argument("--bitrate", type=count, default=1_000_000,
                   help="the bus's bit rate, for the config and its rate (default 1000000)")
    p.add_argument("-o", "--output", metavar="FILE", help="write here (default: stdout)")
    p.set_defaults(func=_init_config)
