"""``rocoma-can init-config``: a run config from what a scan found on the bus.

Each node the scan found is matched to a device file in ``--eds-dir`` by the rule bring-up
checks a drive's identity with (drivers.files.identity.file_fit): a file that names the
vendor-ID and product code its identity object (0x1018) reports is made for it (a
matching revision, then a DCF commissioned for that node id, win among several); a file
bring-up would refuse for it is not; one that names too little (no product number, no
vendor) may fit: it is offered, with what it leaves open and the ``--eds NODE=FILE`` that
picks it. A chosen CiA 402 drive becomes a drive entry fitted to its file the way the demo
fits one (the modes it can run, its scaling, every axis of a multi-axis device) and
carries the identity it was seen with, so bring-up refuses a drive that is not this one
(swapped node ids or cables). The rest are comments: nodes no file is made for, devices
that are not drives, two devices at one node id, drives the manager could not supervise
(they would keep running when the manager dies: left out until someone decides so, in
writing). The rate is the highest of 1000, 500, 250, 100 Hz whose worst-case bus load fits.
The output is checked like any config before it is written: what check-config refuses is
never written; an existing file is replaced only with ``--force``, and kept beside it.

Safe defaults throughout: the manager starts latched (``estop_must_be_cleared``), the one
controller holds the pose it finds (pd without a target), joint names say they are
placeholders, and limits are left for a person to fill in.
"""
from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from .console import err
from .device_match import DeviceFileInfo, index_device_files, match, read_file_info, shown_name
from .exit_codes import FAILED, OK, USAGE
from .scan import bus_options, on_bus

if TYPE_CHECKING:  # the verb imports canopen when it runs: `rocoma-can --help` stays fast

    from ..drivers.files.identity import Identity

#: rates tried, highest first
RATES = (1000, 500, 250, 100)
#: CiA 402 in the low 16 bits of the device type (0x1000)
CIA402 = 402
MANAGER_NODE_IDS = (100, 127, 126, 125)


class Found(Protocol):
    """What init-config needs of a node a scan found (drivers.commission.scan.FoundNode)."""
    @property
    def node_id(self) -> int: ...
    @property
    def identity(self) -> Identity: ...
    @property
    def device_type(self) -> int | None: ...
    @property
    def several_devices(self) -> bool: ...
    @property
    def malformed(self) -> tuple[str, ...]: ...


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


def generate(found: Sequence[Found], eds_dir: str | None, interface: str, channel: str,
             bitrate: int, base: str = ".",
             picked: Mapping[int, DeviceFileInfo] | None = None) -> Generated:
    """The commented YAML for ``found`` (device file paths relative to ``base``, the
    directory the YAML will be in), each node's file from ``picked`` (``--eds``) or else
    from ``eds_dir``; NothingToConfigure (a ValueError) when no drive could be
    configured."""
    from ..drivers.files.identity import file_fit
    from .demo.config import emulate
    files, notes = index_device_files(eds_dir) if eds_dir is not None else ([], [])
    unread = bool(notes)  # files in DIR not read: one may be the node's
    picked = dict(picked or {})
    notes += [f"--eds {n}={shown_name(f.path)}: no node {n} answered the scan"
              for n, f in sorted(picked.items()) if n not in {node.node_id for node in found}]
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
        if node.several_devices:
            lines.append(f"  # node {node.node_id}: two or more devices answer at node id "
                         f"{node.node_id}: not configured (give each its own node id: "
                         "rocoma-can lss)")
            continue
        if "0x1000:0" in node.malformed:
            lines.append(f"  # {seen}: its device type (0x1000) came malformed "
                         "(rocoma-can scan shows it): not configured")
            continue
        if node.device_type is not None and node.device_type & 0xFFFF != CIA402:
            lines.append(f"  # {seen}: device type 0x{node.device_type:08X}, not a CiA 402 "
                         "drive: not configured")
            continue
        how = ""
        if node.node_id in picked:
            chosen = picked[node.node_id]
            fit = file_fit(chosen.od, ident, chosen.path)
            if fit.wrong is not None:
                lines.append(f"  # node {node.node_id}: --eds {Path(chosen.path).name}: "
                             f"{fit.wrong}: not configured")
                continue
            how = "picked by --eds" + (f"; {fit.open}" if fit.open else "")
            others = ""
        else:
            made, may = match(node.node_id, ident, node.device_type, files)
            if not made:
                lines.append(f"  # {seen}: " + _no_file(node.node_id, ident, eds_dir, may,
                                                         unread))
                continue
            chosen = made[0]
            others = ", ".join(Path(f.path).name for f in made[1:])
        try:
            fitted = emulate(chosen.path, 1)
        except ValueError as exc:
            lines.append(f"  # {seen}: {Path(chosen.path).name}: {exc}")
            continue
        guessed = _guessed(chosen.path)
        drive = dict(fitted.drive)
        unsupervised = drive.pop("accept_unsupervised", False)
        lines.append(f"  # node {node.node_id}: {Path(chosen.path).name}"
                     + (f" ({how})" if how else "")
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
        # (a scalar YAML would read as another type is quoted: channel 29536, a Kvaser's)
        f"bus: {_flow({'interface': interface, 'channel': channel, 'bitrate': bitrate})}",
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


def _no_file(node_id: int, identity: Identity, eds_dir: str | None,
             may: Sequence[tuple[DeviceFileInfo, str]], unread: bool = False) -> str:
    """Why no file is chosen for a node: the files that may fit, each with what it leaves
    open and the option that picks it, or that none is there to pick (``unread``: files in
    the folder that were not read, each in a note, one of which may be the node's)."""
    where = f"no file in {eds_dir}" if eds_dir is not None else "no --eds-dir file"
    if not may:
        return (f"{where} is for vendor {_hex(identity.vendor_id)} product "
                f"{_hex(identity.product_code)}: add its EDS/DCF"
                + (" (or fix a file init-config noted as not read)" if unread else "")
                + " and run init-config again")
    offered = ", ".join(f"{Path(f.path).name} ({why})" for f, why in may)
    return (f"{where} names this device; may fit: {offered}: pick one with --eds "
            f"{node_id}={may[0][0].path}")


def _guessed(path: str) -> list[str]:
    """The scaling keys the demo's fit had to guess for this file (no 0x608F / 0x6076)."""
    from ..drivers.files.capabilities import read_capabilities
    from ..drivers.protocol.cia402 import POSITION_ENCODER_RESOLUTION, RATED_TORQUE
    caps = read_capabilities(path, 1)
    return [key for key, ok in (
        ("increments_per_rev", caps.value(POSITION_ENCODER_RESOLUTION, 1)
         and caps.value(POSITION_ENCODER_RESOLUTION, 2)),
        ("rated_torque_nm", caps.value(RATED_TORQUE))) if not ok]


def _fitting_rate(drives: list[dict[str, Any]], interface: str, bitrate: int,
                  notes: list[str]) -> int:
    from ..drivers.plan.config import DriveConfig
    from ..drivers.plan.drive_plan import plan_drives
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
    if args.eds_dir is None and not args.eds:
        problem = "give --eds-dir DIR or --eds NODE=FILE (the drives' EDS/DCF files)"
    elif args.eds_dir is not None and not os.path.isdir(args.eds_dir):
        problem = f"--eds-dir {args.eds_dir}: not a directory"
    elif args.eds_dir is not None:
        try:
            os.listdir(args.eds_dir)
        except OSError as exc:
            problem = f"--eds-dir {args.eds_dir}: cannot read ({exc.strerror or exc})"
        if problem is None and shown_name(args.eds_dir) != args.eds_dir:
            problem = (f"--eds-dir {shown_name(args.eds_dir)}: its path is not UTF-8: a "
                       "config (UTF-8 text) cannot name the files in it")
    if problem is None:
        args.picked, problem = _picked(args.eds)
    if problem is None and args.output:
        why = _not_writable(Path(args.output), args.force)
        problem = f"-o {args.output}: {why}" if why else None
    if problem:  # before the scan, which takes seconds
        err(f"init-config: {problem}")
        return USAGE
    return on_bus(args, lambda bus: _write(args, bus))


def _eds_pick(text: str) -> tuple[int, str]:
    """--eds NODE=FILE as (node id, path); ArgumentTypeError for anything else."""
    node, sep, path = text.partition("=")
    if not sep or not node.strip().isdigit() or not path:
        raise argparse.ArgumentTypeError(f"expected NODE=FILE (a node id and its EDS/DCF), "
                                         f"got {text!r}")
    if not 1 <= int(node) <= 127:
        raise argparse.ArgumentTypeError(f"{text}: node ids are 1..127")
    return int(node), path


def _picked(picks: Sequence[tuple[int, str]]
            ) -> tuple[dict[int, DeviceFileInfo], str | None]:
    """The --eds files, read; the first problem (one line) of one that cannot be used."""
    from ..drivers.files.device_file import DeviceFileError
    out: dict[int, DeviceFileInfo] = {}
    for node, path in picks:
        if node in out:
            return out, f"--eds {node}={path}: node {node} has a file already"
        if shown_name(path) != path:
            return out, (f"--eds {node}={shown_name(path)}: its path is not UTF-8: a config "
                         "(UTF-8 text) cannot name it")
        try:
            out[node] = read_file_info(path)
        except (DeviceFileError, OSError) as exc:
            return out, f"--eds {node}={path}: not read ({exc})"
    return out, None


def _not_writable(path: Path, force: bool) -> str | None:
    """Why the config cannot be written to ``path``, or None (it may still fail later): an
    existing file only with ``force`` (a config edited by hand must not be lost)."""
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
    if what:
        return f"is {what}, not a file to write"
    if not force:
        return (f"exists (a config edited by hand would be lost): --force replaces it, "
                f"keeping it as {_backup(path).name}")
    return None


def _backup(path: Path) -> Path:
    """Where the file at ``path`` is kept when replaced: NAME.bak, else the first free
    NAME.bak.N (an older backup is never overwritten)."""
    candidate, n = path.with_name(path.name + ".bak"), 0
    while candidate.exists() or candidate.is_symlink():
        n += 1
        candidate = path.with_name(f"{path.name}.bak.{n}")
    return candidate


def _replace(path: Path, text: str) -> Path | None:
    """Write ``text`` to ``path`` whole or not at all (a file beside it, renamed over it);
    an existing file is first moved to its backup, which is returned (None: there was
    none). OSError when it cannot."""
    temporary = path.with_name(f".{path.name}.init-config.tmp")
    temporary.write_text(text, encoding="utf-8")
    kept = None
    try:
        if path.exists():
            kept = _backup(path)
            os.replace(path, kept)
        os.replace(temporary, path)
    finally:
        if temporary.exists():
            temporary.unlink()
    return kept


def _write(args: argparse.Namespace, bus: Any) -> int:
    import yaml

    from ..drivers.commission.scan import scan
    from ..errors import ConfigError
    from ..runtime.config import validate
    found = scan(bus, timeout=args.timeout, listen=args.listen)
    base = Path(args.output).resolve().parent if args.output else Path.cwd()
    try:
        made = generate(found, args.eds_dir, args.interface, args.channel, args.bitrate,
                        str(base), args.picked)
    except ValueError as exc:
        for note in getattr(exc, "notes", ()):  # files not read: maybe why none matched
            err(f"init-config: note: {note}")
        err(f"init-config: {exc}")
        return FAILED
    try:
        validate(yaml.safe_load(made.text), args.output or "<init-config>", base)
    except ConfigError as exc:  # a bug of ours: never hand out a config check-config refuses
        err(f"init-config: the generated config does not pass its own check: {exc}")
        return FAILED
    for note in made.notes:
        err(f"init-config: note: {note}")
    if args.output:
        try:
            kept = _replace(Path(args.output), made.text)
        except OSError as exc:
            err(f"init-config: -o {args.output}: cannot write ({exc.strerror or exc})")
            return USAGE
        if kept is not None:
            print(f"init-config: {args.output} existed: kept as {kept}", file=sys.stderr)
        print(f"init-config: {made.drives} drive(s) written to {args.output}; next: "
              f"rocoma-can check-config {args.output}", file=sys.stderr)
    else:
        sys.stdout.write(made.text)
    return OK


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from ..drivers.commission.scan import LISTEN, TIMEOUT  # constants only: no canopen import
    from .args import count, seconds
    p = subparsers.add_parser(
        "init-config", help="a run config from a scan of the bus and a folder of EDS/DCF files",
        description="Scan the bus (as `rocoma-can scan`), match each node to a file in "
                    "--eds-dir by its vendor-ID and product code (the rule bring-up checks "
                    "identities with), and write a commented config that check-config "
                    "accepts: a drive per matched CiA 402 node with the identity it was seen "
                    "with; the rest as comments, with the files that may fit and why.")
    bus_options(p, TIMEOUT, "seconds to wait for each SDO answer")
    p.add_argument("--listen", type=seconds, default=LISTEN, metavar="S",
                   help=f"listen for heartbeats this long first (default {LISTEN:g})")
    p.add_argument("--eds-dir", default=None, metavar="DIR",
                   help="the drives' EDS/DCF files (matched by vendor and product)")
    p.add_argument("--eds", type=_eds_pick, action="append", default=[],
                   metavar="NODE=FILE",
                   help="this node's file, whatever --eds-dir offers (one that names too "
                        "little to be matched; repeat per node); refused when bring-up "
                        "would refuse it")
    p.add_argument("--bitrate", type=count, default=1_000_000,
                   help="the bus's bit rate, for the config and its rate (default 1000000)")
    p.add_argument("-o", "--output", metavar="FILE", help="write here (default: stdout)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing -o FILE, keeping it as FILE.bak (or .bak.N)")
    p.set_defaults(func=_init_config)
