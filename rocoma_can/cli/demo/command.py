"""``rocoma-can demo``: the whole system on in-process CAN buses.

Simulated CiA 402 drives (in a process of their own or stepped by the loop: drives.py),
the control loop with the manager and its CANopen node, and an "operator" that talks to the
manager only the way another CAN node would (SDO and raw frames). The walk-through:
bring-up, clear, switch to pd, switch to trajectory (bumpless, by swap state), a drive
fault -> emergency controller (damp), a second fault -> failproof torque-off, recovery of
the drives, a switch back to pd, an e-stop by a raw CAN frame, and the SIGTERM-like stop of
the loop, which ends in torque-off frames. Each step checks what it should; the exit code
is 0 only when every step did. An operator's e-stop (Foxglove, Zenoh, ``rocoma-can
estop``) ends the walk-through early with the robot left stopped (OutsideStop). The
command records the run (every frame, every cycle, every manager event) and plots it, and
prints where both went.

This module is the verb: its options, read into a DemoOptions, and its exit code; the run
itself is walkthrough.py's Walkthrough.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

from ...drivers.protocol.wire import MAX_DATA_BITRATE
from ...errors import ConfigError, RocomaError, SimulatorFailed
from ...record.can_log import RecordingError
from ..args import count, positive, rt_priority, seconds
from ..console import ThreadedLines
from ..exit_codes import FAILED, INTERRUPTED, OK, PIPE_CLOSED, USAGE
from ..foxglove_args import add_foxglove_options, foxglove_from_args
from ..state_dirs import default_flight_dir, state_dir
from .config import DEFAULT_INTERFACE, FD_BITRATE, FD_DATA_BITRATE, default_buses
from .drives import SIM_CHOICES, check_choice
from .report import DemoReport
from .walkthrough import DemoOptions, Walkthrough


def default_record_dir() -> Path:
    """A new directory per run under the state directory's demo/ (state_dirs.state_dir):
    named for its start, numbered after a run started in the same second (a recording is
    never written over)."""
    first = state_dir("demo", time.strftime("%Y%m%d-%H%M%S"))
    path, n = first, 1
    while path.exists():
        n += 1
        path = first.with_name(f"{first.name}-{n}")
    return path


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "demo", help="run the embedded demo (in-process bus, simulated drives)",
        description=__doc__.split("\n\n")[0])
    p.add_argument("--drives", type=int, default=6, help="simulated drives (default 6)")
    p.add_argument("--buses", type=int, default=None,
                   help="in-process CAN buses the drives are spread over (default: one up to "
                        "6 drives, else one per 3 drives)")
    p.add_argument("--rate", type=positive, default=200.0, help="loop rate, Hz (default 200)")
    p.add_argument("--eds", default=None, metavar="FILE",
                   help="the simulated drives emulate this EDS/DCF: the demo uses the modes "
                        "it supports and says which steps it skips and why")
    p.add_argument("--fd", action="store_true",
                   help="CAN FD buses (1 Mbit/s arbitration, --data-bitrate data phase): FD "
                        "frames both ways, the drives' PDOs up to 64 bytes (one RPDO and one "
                        "TPDO a cycle), the bus load checked as for real buses")
    p.add_argument("--data-bitrate", type=count, default=None, metavar="BIT/S",
                   help=f"the data phase of the --fd buses (default {FD_DATA_BITRATE})")
    p.add_argument("--interface", choices=("inproc", "virtual"), default=DEFAULT_INTERFACE,
                   help="in-process bus: inproc (default; one copy per frame, fit for "
                        "1 kHz) or python-can's virtual (a copy per frame and receiver)")
    p.add_argument("--sim", choices=SIM_CHOICES, default="loop",
                   help="where the simulated drives run: loop (default: stepped by the loop "
                        "after each write) or process (their own, so the loop pays only for "
                        "their frames, as with real drives: for a host with a core for each "
                        "busy process; inproc buses)")
    p.add_argument("--duration", type=seconds, default=16.0,
                   help="the walk-through's length, s, from bring-up to the loop's stop: its "
                        "pauses stretch to end it then (default 16; steps slower than their "
                        "share make it longer; set-up and the plot come on top)")
    p.add_argument("--record", default=None, metavar="DIR",
                   help="where the recording and its plot go (default: a new directory "
                        "under ~/.local/state/rocoma-can/demo/)")
    p.add_argument("--no-record", action="store_true", help="no recording, no plot")
    p.add_argument("--flight-dir", default=None, metavar="DIR",
                   help="where each e-stop's flight record goes, as with run (default: "
                        "flight/ in the recording's directory, or run's default without one)")
    p.add_argument("--no-flight", action="store_true", help="no flight recorder")
    p.add_argument("--priority", type=rt_priority, default=None, metavar="1..99",
                   help="run the loop's thread SCHED_FIFO at this priority, as a robot's "
                        "realtime.priority (needs CAP_SYS_NICE or an rtprio limit; refused: "
                        "said, and the demo runs at normal priority). Default: normal")
    add_foxglove_options(p)
    from ...ros2.config import add_ros2_options
    add_ros2_options(p, connect=True)
    p.add_argument("--zenoh-listen", default=None, metavar="ENDPOINT",
                   help="serve the demo's manager on Zenoh as rocoma/demo at ENDPOINT "
                        "(e.g. tcp/127.0.0.1:7447): watch and e-stop it from another shell")
    p.set_defaults(func=_main)


def _main(args: argparse.Namespace) -> int:
    try:
        options = _options(args)
    except _Usage as usage:
        for line in usage.lines:
            print(f"demo: {line}", flush=True)
        return USAGE
    out = ThreadedLines()
    try:
        report = Walkthrough(options, out).run()
    except (ValueError, RocomaError, RecordingError) as exc:
        return _not_run(exc, None if options.record is None else Path(options.record))
    hint = path_hint()
    if hint is not None:
        out(hint)
    return _exit_code(report, out)


class _Usage(Exception):
    """A command line the demo refuses: its lines, each said as ``demo: LINE``."""

    def __init__(self, *lines: str) -> None:
        super().__init__(*lines)
        self.lines = lines


def _options(args: argparse.Namespace) -> DemoOptions:
    """The command line as the walk-through's options (its recording's directory made);
    _Usage for one it refuses, before anything runs."""
    _check_numbers(args)
    try:
        foxglove = foxglove_from_args(args)
    except ValueError as exc:
        raise _Usage(str(exc)) from None
    from ...ros2.config import from_args as ros2_from_args
    problems: list[str] = []
    ros2 = ros2_from_args(args, None, problems)
    if problems:
        raise _Usage(*problems)
    record = None if args.no_record else Path(args.record or default_record_dir())
    if record is not None:
        try:
            record.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise _Usage(f"--record {record}: cannot create the directory: {exc}") from None
    flight = None if args.no_flight else Path(
        args.flight_dir or (record / "flight" if record is not None else default_flight_dir()))
    return DemoOptions(
        drives=args.drives, rate=args.rate, duration=args.duration, buses=args.buses,
        interface=args.interface, eds=args.eds, record=record,
        zenoh_listen=args.zenoh_listen, flight=flight, foxglove=foxglove,
        data_bitrate=(args.data_bitrate or FD_DATA_BITRATE) if args.fd else None,
        sim=args.sim, priority=args.priority, ros2=ros2)


def _check_numbers(args: argparse.Namespace) -> None:
    """_Usage for drives, buses, rate, duration or a data bit rate out of the demo's range,
    or a --sim its --interface cannot do."""
    buses = default_buses(args.drives) if args.buses is None else args.buses
    if not 2 <= args.drives <= 32 or not 10 <= args.rate <= 2000 or not args.duration > 0 \
            or not 1 <= buses <= args.drives // 2:
        raise _Usage("--drives 2..32, --rate 10..2000 Hz, --duration > 0, --buses 1.."
                     "drives/2 (the walk-through faults two drives of the first bus)")
    if args.data_bitrate is not None and (not args.fd or not FD_BITRATE <= args.data_bitrate
                                          <= MAX_DATA_BITRATE):
        raise _Usage(f"--data-bitrate: the data phase of --fd buses, {FD_BITRATE}.."
                     f"{MAX_DATA_BITRATE} bit/s, got {args.data_bitrate}"
                     + ("" if args.fd else " without --fd"))
    try:
        check_choice(args.sim, args.interface)
    except ValueError as exc:
        raise _Usage(str(exc)) from None


def _not_run(exc: ValueError | RocomaError | RecordingError, record: Path | None) -> int:
    """The demo could not start: said in one line (a config's problems, one each); the
    recording's directory it made, removed while empty. The exit code."""
    if isinstance(exc, SimulatorFailed):  # its drives' process did not start
        print(f"demo: {exc}", flush=True)
        return FAILED
    if isinstance(exc, RecordingError):  # --record DIR: not writable, or an earlier recording
        print(f"demo: --record: {exc}", flush=True)
        return USAGE
    if isinstance(exc, ConfigError):  # --zenoh-listen that is no endpoint: "demo: ..."
        for problem in exc.problems:
            print(problem, flush=True)
    elif isinstance(exc, ValueError):  # a file that is no EDS, or one it cannot drive
        print(f"demo: --eds: {exc}", flush=True)
    else:  # Zenoh: not installed, the endpoint taken
        print(f"demo: {exc}", flush=True)
    if record is not None and not any(record.iterdir()):
        record.rmdir()  # it did not run: no empty recording directory left behind
    return USAGE


def _exit_code(report: DemoReport, out: ThreadedLines) -> int:
    if out.gone:
        return PIPE_CLOSED
    if report.interrupted:
        return INTERRUPTED
    return OK if report.ok else FAILED


def path_hint() -> str | None:
    """How to get the ``rocoma-can`` command when the shell would not find it.

    ``bash tools/demo`` runs .venv/bin/rocoma-can without activating the venv, and the
    README's next step is ``rocoma-can check-config``: "command not found", unless this
    says how. None when a ``rocoma-can`` is on PATH."""
    if shutil.which("rocoma-can") is not None:
        return None
    activate = Path(sys.prefix) / "bin" / "activate"
    install = f"pip install -e '.[{README_EXTRAS}]' from a checkout"
    if not activate.is_file():
        return f"rocoma-can: not on PATH; for the README's commands: {install}"
    shown = os.path.relpath(activate) if activate.is_relative_to(Path.cwd()) else activate
    return f"rocoma-can: not on PATH; for the README's commands: . {shown} (or {install})"


#: the extras the README's commands need: recording and plots, status --watch, Zenoh, the
#: Foxglove live view (run --foxglove, demo --foxglove)
README_EXTRAS = "record,plot,live,zenoh,foxglove,ros2"
