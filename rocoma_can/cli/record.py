"""``rocoma-can record`` (raw CAN to a candump/ASC/BLF file), ``rocoma-can export`` (an
MCAP trace to CSV) and ``rocoma-can plot`` (a trace to a PNG). They work beside a running
manager or on their own; imports are deferred so ``rocoma-can --help`` stays quick."""
from __future__ import annotations

import argparse
import csv
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .args import channel_name, seconds
from .console import err
from .exit_codes import FAILED, OK, USAGE
from .hints import REACH_ELSEWHERE, no_socketcan_hint

if TYPE_CHECKING:
    from ..record.can_log import FrameLog



def _record(args: argparse.Namespace) -> int:
    from ..drivers.link.bus import open_bus
    from ..record.can_log import BusRecording, RecordingError, check_path
    try:
        check_path(args.file)
        bus = open_bus(args.interface, args.channel, receive_own_messages=False)
    except (RecordingError, OSError) as exc:
        err(str(exc) + no_socketcan_hint(exc, REACH_ELSEWHERE))
        return USAGE
    try:
        recording = BusRecording(bus, args.file)
    except RecordingError as exc:
        bus.shutdown()
        err(str(exc))
        return USAGE
    stop = threading.Event()
    flag = {"signalled": False}

    def on_signal(signum: int, frame: object) -> None:  # no lock in a handler: a flag
        flag["signalled"] = True
    previous = ({sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
                if threading.current_thread() is threading.main_thread() else {})
    print(f"recording {args.interface}:{args.channel} to {args.file} (Ctrl-C to stop)",
          flush=True)
    progress = _progress(recording.log)
    try:
        waited = 0.0
        while not flag["signalled"] and (args.duration is None or waited < args.duration):
            stop.wait(0.1)
            waited += 0.1
            progress(waited)
            if recording.log.error:
                break
    finally:
        progress(None)
        recording.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log = recording.log
    print(f"{log.frames} frames written to {log.path}"
          + (f", {log.dropped} dropped" if log.dropped else ""), flush=True)
    if log.error:
        err(log.error)
        return FAILED
    return OK


def _progress(log: FrameLog) -> Callable[[float | None], None]:
    """In a terminal with rich (``rocoma-can[live]``): a live line of frames written, time
    and drops; elsewhere nothing (the final count is printed either way)."""
    if not sys.stdout.isatty():
        return lambda waited: None
    try:
        from rich.console import Console
    except ImportError:
        return lambda waited: None
    status = Console().status("recording ...")
    status.start()

    def update(waited: float | None) -> None:
        if waited is None:
            status.stop()
            return
        status.update(f"recording: {log.frames} frames in {waited:.0f} s"
                      + (f", {log.dropped} dropped" if log.dropped else ""))
    return update


def _export(args: argparse.Namespace) -> int:
    from ..record.trace import TraceError
    source = Path(args.file)
    if args.out == "-":
        return _export_to_stdout(source)
    out = Path(args.out) if args.out else source.with_suffix(".csv")
    if out.resolve() == source.resolve():
        err(f"{out}: the CSV would overwrite the trace it is read from; give --csv FILE")
        return USAGE
    # written beside, then renamed: a failed export leaves an earlier CSV as it was
    part = out.with_name(out.name + ".part")
    notes: list[str] = []
    try:
        with open(part, "w", newline="") as stream:
            rows = _write_csv(source, stream, notes)
        os.replace(part, out)
    except ImportError:
        _discard(part)
        err("reading MCAP needs the mcap package: pip install 'rocoma-can[record]'")
        return USAGE
    except TraceError as exc:
        _discard(part)
        err(f"{source}: not a rocoma-can trace: {exc}")
        return USAGE
    except OSError as exc:  # the CSV's side (the trace's failures are TraceErrors)
        _discard(part)
        err(f"{out}: cannot write the CSV: {exc.strerror or exc}")
        return USAGE
    for note in notes:
        err(f"{source}: {note}")
    print(f"{rows} cycles written to {out}", flush=True)
    return OK


def _export_to_stdout(source: Path) -> int:
    """``--csv -``: the rows on stdout for a pipe (``| head``, ``| csvlook``), what is said
    on stderr; a trace that turns out unreadable after rows went out is said, exit 2."""
    from ..record.trace import TraceError
    notes: list[str] = []
    try:
        rows = _write_csv(source, sys.stdout, notes)
        sys.stdout.flush()
    except ImportError:
        err("reading MCAP needs the mcap package: pip install 'rocoma-can[record]'")
        return USAGE
    except TraceError as exc:
        err(f"{source}: not a rocoma-can trace: {exc}")
        return USAGE
    for note in notes:
        err(f"{source}: {note}")
    err(f"{rows} cycles written to stdout")
    return OK


def _write_csv(source: Path, stream: Any, notes: list[str]) -> int:
    """The cycles of ``source`` as CSV rows on ``stream`` (a header first); the number of
    cycles. Per-joint columns are ``FIELD[JOINT]`` with the joints' names from the trace
    (their numbers where a trace carries none), as the arrays appear in PlotJuggler. A
    file cut short is written up to the cut, said in ``notes``."""
    from ..record.trace import CYCLE_TOPIC, JOINT_FIELDS, SCALARS, read_trace, recorded_joint_names
    writer = csv.writer(stream)
    rows = 0
    for topic, log_time, msg in read_trace(str(source), notes):
        if topic != CYCLE_TOPIC:
            continue
        if rows == 0:
            joints = len(msg["position"])  # every row alike: read_trace checked them
            names = recorded_joint_names(str(source), joints) or [str(j) for j in range(joints)]
            scalars = [k for k in SCALARS if k in msg]  # (a trace from before ``cpu``)
            writer.writerow(["log_time_ns", *scalars,
                             *(f"{f}[{name}]" for f in JOINT_FIELDS for name in names)])
        writer.writerow([log_time, *(msg.get(k, "") for k in scalars),
                         *(v for f in JOINT_FIELDS for v in msg[f])])
        rows += 1
    return rows


def _discard(part: Path) -> None:
    """Remove a partial CSV where there is one: a path that could not be opened (a parent
    that is a file) cannot be removed either, and that is no second error."""
    try:
        part.unlink(missing_ok=True)
    except OSError:
        pass


def _plot(args: argparse.Namespace) -> int:
    from ..record.plot import PlotError, plot
    notes: list[str] = []
    try:
        path = plot(args.file, args.out or None, notes=notes)
    except PlotError as exc:
        err(str(exc))
        return USAGE
    for note in notes:
        err(f"{args.file}: {note}")
    print(f"plot written to {path}", flush=True)
    return OK


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "record", help="record every frame of a bus to FILE (.log candump, .asc, .blf)",
        description="A passive listener: works beside any running manager. Replay a .log "
                    "with `canplayer` or `python -m can.player`.")
    p.add_argument("file", help="FILE.log (candump -L), FILE.asc or FILE.blf")
    p.add_argument("--interface", default="socketcan", help="python-can interface (socketcan)")
    p.add_argument("--channel", type=channel_name, default="can0", help="CAN channel (can0)")
    p.add_argument("--duration", type=seconds, default=None, metavar="S",
                   help="stop after S seconds (default: Ctrl-C / SIGTERM)")
    p.set_defaults(func=_record)
    p = subparsers.add_parser("export", help="an MCAP trace (run --record, a flight record) "
                                             "to CSV, one row per cycle")
    p.add_argument("file", help="FILE.mcap")
    p.add_argument("--csv", dest="out", nargs="?", const="", default="", metavar="OUT",
                   help="the CSV file (default: FILE.csv; - for stdout)")
    p.set_defaults(func=_export)
    p = subparsers.add_parser(
        "plot", help="a trace (run --record, a flight record, the demo's) as one PNG",
        description="Manager state band with controllers and e-stops, joint positions with "
                    "targets, torques, cycle period and jitter histogram.")
    p.add_argument("file", help="FILE.mcap")
    p.add_argument("--out", default="", metavar="PNG", help="the PNG (default: FILE.png)")
    p.set_defaults(func=_plot)
