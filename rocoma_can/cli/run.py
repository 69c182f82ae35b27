"""``rocoma-can run`` and ``rocoma-can check-config``: the manager from a YAML config, and
the config checked without running it (every problem listed, then what the drives' files
allow and what bring-up will require).

Exit codes (for shell scripts):
  0  done (run: stopped by Ctrl-C / SIGTERM after its torque-off, or its --duration)
  1  bring-up did not finish, or the recording failed
  2  usage or configuration error (bad YAML, overloaded bus, cannot open the bus)
  130  a stop signal before or during bring-up, or while closing
"""
from __future__ import annotations

import argparse
import faulthandler
import importlib.util
import logging
import signal
from typing import TYPE_CHECKING, Any

from ..audit import AUDIT
from ..errors import BusTaken, ConfigError
from ..fleet.bridge import FleetError
from ..fleet.config import FleetConfig, parse_fleet
from ..live.foxglove import FoxgloveError, describe_view
from ..ros2.config import add_ros2_options
from ..ros2.config import from_args as ros2_from_args
from .args import flight_seconds, seconds
from .exit_codes import FAILED, INTERRUPTED, OK, USAGE
from .foxglove_args import add_foxglove_options, config_taken_as_address, foxglove_from_args
from .hints import no_socketcan_hint
from .main import interrupted_by
from .state_dirs import default_flight_dir

if TYPE_CHECKING:  # check-config and --help do not import the runtime (a fast start)
    from ..runtime.config import RuntimeConfig
    from ..runtime.loop import TimingSummary
    from ..runtime.system import Runtime


#: ``run``'s console (cli/console.py): its own lines on stdout with the audit trail, its
#: errors on stderr, both in the one format with the time in front
say = logging.getLogger(AUDIT)
log = logging.getLogger(__name__)


def _check_config(args: argparse.Namespace) -> int:
    from ..runtime.another_manager import what_run_listens_for
    from ..runtime.config import load
    try:
        config = load(args.config)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem, flush=True)
        print(f"{len(exc.problems)} problem(s)", flush=True)
        return USAGE
    print(f"{args.config}: ok: {len(config.drives)} drives on {_buses(config)} at "
          f"{config.rate:g} Hz, manager node {config.manager.node_id}, "
          + (f"e-stop COB-ID 0x{config.manager.estop_cob_id:03X}"
             if config.manager.estop_cob_id else "no e-stop frame (manager.estop_cob_id: 0)"),
          flush=True)
    for note in config.notes:
        print(f"note: {note}", flush=True)
    print(f"note: {what_run_listens_for(config)}", flush=True)
    several = len(config.buses) > 1
    for name, load_ in config.loads.items():
        print(f"bus load{f' {name}' if several else ''}: {load_.explain()}", flush=True)
    if args.drives:  # each drive as its EDS/DCF lets rocoma-can drive it
        for plan in config.plans.values():
            for line in plan.report():
                print(line, flush=True)
    else:  # what is degraded, and what bring-up will require, is worth a line each
        for plan in config.plans.values():
            for note in plan.notes:
                print(f"drive {plan.drive.name!r}: {note}", flush=True)
            print(f"drive {plan.drive.name!r}: {plan.identity.describe()}", flush=True)
    return OK


def _buses(config: RuntimeConfig) -> str:
    """"socketcan:can0", or per bus "left (socketcan:can0, 3 drives), ..."."""
    if len(config.buses) == 1:
        b = config.bus
        return f"{b.interface}:{b.channel}" + (" (CAN FD)" if b.fd else "")
    return ", ".join(f"{b.label} ({b.interface}:{b.channel}{', CAN FD' if b.fd else ''}, "
                     f"{len(config.drives_on(b))} drives)" for b in config.buses)



def recording_available() -> bool:
    """The MCAP writer (the optional extra rocoma-can[record]) is installed."""
    return importlib.util.find_spec("mcap") is not None



def _run(args: argparse.Namespace) -> int:
    """``rocoma-can run``: one outcome per phase of a stop signal (Ctrl-C, SIGTERM), each
    said in one line (docs/cli.md, "Stopping run"): before bring-up nothing was sent to the
    drives (exit 130); during bring-up the loop's torque-off, exit 130; while running the
    loop's torque-off, exit 0 (the way a run is ended); while closing, after the
    torque-off, what was cut short, exit 130. Before bring-up is every step up to the
    loop's start, its imports and option checks too: a Ctrl-C between two of them said
    main()'s bare ``interrupted (SIGINT)``."""
    phase = ["before bring-up: nothing was sent to the drives"]
    try:
        return _run_phases(args, phase)
    except KeyboardInterrupt:
        return _interrupted(phase[0])


def _run_phases(args: argparse.Namespace, phase: list[str]) -> int:
    """_run's steps; ``phase[0]``: what a stop signal now interrupts."""
    from ..ros2.node import Ros2Error
    from ..runtime.config import load
    from ..runtime.system import Runtime
    try:  # the options first: nothing is read or started for a command line that is wrong
        foxglove = foxglove_from_args(args)
    except ValueError as exc:
        log.error("%s", exc)
        return USAGE
    try:
        config = load(args.config, rate=args.rate)
    except ConfigError as exc:
        for problem in exc.problems:
            log.error("%s", problem + (" (with --rate)" if args.rate is not None else ""))
        return USAGE
    try:
        config.fleet = fleet_from_args(args, config.fleet)
    except ConfigError as exc:
        for problem in exc.problems:
            log.error("%s", problem)
        return USAGE
    problems: list[str] = []
    config.ros2 = ros2_from_args(args, config.ros2, problems)
    for problem in problems:
        log.error("%s", problem)
    if problems:
        return USAGE
    flight = None if args.no_flight else args.flight_dir
    if flight is not None and not recording_available():
        log.warning("flight recorder off: it writes MCAP, pip install 'rocoma-can[record]'")
        flight = None
    if args.record and not recording_available():
        log.error("--record writes MCAP: pip install 'rocoma-can[record]'")
        return USAGE
    try:
        runtime = Runtime(config, record=args.record, flight=flight,
                          flight_seconds=args.flight_seconds, announce=say.info,
                          foxglove=foxglove)
    except (OSError, ValueError, FleetError, FoxgloveError, BusTaken, Ros2Error) as exc:
        log.error("%s", str(exc) + no_socketcan_hint(exc))
        return USAGE
    with runtime:  # (closed whatever interrupts it, from its first line on)
        if hasattr(signal, "SIGUSR2"):  # `kill -USR2 PID`: every thread's stack (a hang)
            faulthandler.register(signal.SIGUSR2, all_threads=True)
        _say_started(runtime, args)
        # The loop takes Ctrl-C / SIGTERM before run says its state: a stop after that line
        # is the loop's (torque-off, "stopped ... during bring-up"), never an interrupt of
        # the moment before the loop starts.
        restore = runtime.loop.install_signal_handlers()
        try:
            phase[0] = "while closing, after the torque-off"
            _say_state(runtime)
            summary = runtime.run(duration=args.duration, signals=False)
        except OSError as exc:
            log.error("%s", str(exc) + no_socketcan_hint(exc))
            return USAGE
        finally:
            restore()
        return _stopped(runtime, summary)


def _interrupted(when: str) -> int:
    log.error("interrupted (%s) %s", interrupted_by(), when)
    return INTERRUPTED


def _say_started(runtime: Runtime, args: argparse.Namespace) -> None:
    config = runtime.config
    say.info("running %d drives at %g Hz on %s, manager node %d (Ctrl-C / SIGTERM: "
             "torque-off, then exit)", len(config.drives), config.rate, _buses(config),
             config.manager.node_id)
    if runtime.flight is not None:
        say.info("flight recorder: the last %g s before every e-stop go to %s",
                 args.flight_seconds, runtime.flight.directory)
    if runtime.recording is not None:
        say.info("recording every frame and cycle to %s", args.record)
    if runtime.fleet is not None:
        f = runtime.fleet.config
        say.info("on Zenoh as %s (%s%s; switch/clear/recover %s)", f.prefix, f.mode,
                 "".join(f", {k} {', '.join(v)}" for k, v in (("listen", f.listen),
                                                              ("connect", f.connect)) if v),
                 "allowed" if f.allow_commands else "refused")
    # (running without Zenoh, zenoh.required false: said by the runtime as it found it)
    if runtime.foxglove is not None:
        say.info("%s", describe_view(runtime.foxglove))
    if runtime.ros2 is not None:
        from ..ros2.node import describe_node
        say.info("%s", describe_node(runtime.ros2))
    elif runtime.ros2_error:
        log.warning("running without the ROS 2 node: %s", runtime.ros2_error)


def _say_state(runtime: Runtime) -> None:
    """run's last line before the loop starts: from it on, a stop is the loop's."""
    m = runtime.manager
    say.info("state %s, controller %s%s", m.state.name, m.active_controller_name,
             ", e-stop latched (rocoma-can clear clears it)" if m.estop_latched else "")


def _stopped(runtime: Runtime, summary: TimingSummary) -> int:
    """The run's last line (how it stopped, its cycles) and its exit code (see _run)."""
    hw, reason = runtime.hardware, runtime.loop.stop_reason
    drives = hw.drive_status()
    failed = [d.name for d in drives if d.phase == "FAILED"]
    starting = [f"{d.name} ({d.phase})" for d in drives if d.phase not in ("READY", "FAILED")]
    if reason.startswith("signal ") and not hw.started_up:
        say.info("stopped (%s) during bring-up, torque-off sent; not brought up: %s; %s",
                 reason, ", ".join(starting + [f"{n} (FAILED)" for n in failed]),
                 summary.line())
        return INTERRUPTED
    say.info("stopped (%s); %s", reason, summary.line())
    if failed or starting:  # each failure was said as it happened: counted, not repeated
        log.error("bring-up did not finish: %s", "; ".join(
            part for part in (f"{len(failed)} of {len(drives)} drives failed (said above)"
                              if failed else "",
                              f"still starting: {', '.join(starting)}" if starting else "")
            if part))
        return FAILED
    if runtime.recording is not None and runtime.recording.errors:
        return FAILED  # said as it happened (one warning); the record has a hole
    return OK

def fleet_from_args(args: argparse.Namespace, fleet: FleetConfig | None) -> FleetConfig | None:
    """The config's zenoh: section with the command line's --zenoh* flags over it (any of
    them turns Zenoh on), checked as the section is: ConfigError lists what is wrong."""
    flags: dict[str, Any] = {}
    if args.zenoh:
        flags["prefix"] = args.zenoh
    if args.zenoh_mode:
        flags["mode"] = args.zenoh_mode
    if args.zenoh_connect:
        flags["connect"] = args.zenoh_connect
    if args.zenoh_listen:
        flags["listen"] = args.zenoh_listen
    if args.zenoh_no_multicast:
        flags["multicast"] = False
    if args.zenoh_allow_commands:
        flags["allow_commands"] = True
    if args.zenoh_deadman:
        flags["deadman"] = args.zenoh_deadman
    if not flags and args.zenoh is None:
        return fleet
    if args.ros2 and args.zenoh is None and fleet is None and list(flags) == ["connect"]:
        return None  # --ros2 --zenoh-connect: the ROS 2 node's router, no fleet bridge
    problems: list[str] = []
    merged = parse_fleet(flags, problems, where="--zenoh", base=fleet)
    if problems:
        raise ConfigError(problems)
    return merged



def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("run", help="run the manager from a YAML config",
                              hint=config_taken_as_address)
    p.add_argument("config", help="YAML file (see docs/configuration.md)")
    p.add_argument("--duration", type=seconds, default=None, help="stop after this many s")
    p.add_argument("--rate", type=float, default=None, help="override the loop rate, Hz")
    p.add_argument("--record", default=None, metavar="DIR",
                   help="write every cycle, event and frame (DIR/trace.mcap) and every "
                        "frame again as candump (DIR/<bus>.log) as they happen")
    p.add_argument("--flight-dir", default=str(default_flight_dir()), metavar="DIR",
                   help="where the flight recorder writes (default %(default)s)")
    p.add_argument("--flight-seconds", type=flight_seconds, default=10.0, metavar="S",
                   help="seconds the flight recorder keeps before an e-stop (10)")
    p.add_argument("--no-flight", action="store_true", help="no flight recorder")
    g = p.add_argument_group("Zenoh (the config's zenoh: section; these override it)")
    g.add_argument("--zenoh", nargs="?", const="", default=None, metavar="PREFIX",
                   help="serve the manager on Zenoh (prefix default rocoma/<host>)")
    g.add_argument("--zenoh-mode", choices=("peer", "client"), default=None)
    g.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT")
    g.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT")
    g.add_argument("--zenoh-no-multicast", action="store_true",
                   help="no multicast scouting")
    g.add_argument("--zenoh-allow-commands", action="store_true",
                   help="accept switch, clear and recover over Zenoh (e-stops always are)")
    g.add_argument("--zenoh-deadman", default=None, metavar="KEY",
                   help="e-stop when this liveliness token vanishes (once seen)")
    add_foxglove_options(p)
    add_ros2_options(p)
    p.set_defaults(func=_run, clock=True, audit=True)  # its console: the run's record

    p = subparsers.add_parser("check-config", help="validate a YAML config, list every problem")
    p.add_argument("config")
    p.add_argument("--drives", action="store_true",
                   help="per drive: modes, feedback, PDOs, what its EDS/DCF lacks and what "
                        "happens when the manager is lost")
    p.set_defaults(func=_check_config)

