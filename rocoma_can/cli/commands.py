"""Sub-commands ``run``, ``check-config`` and the client commands that talk to a running
manager over the bus: ``switch``, ``estop``, ``failproof``, ``clear``, ``recover``, ``home``,
``status``, ``list``.

Exit codes (for shell scripts):
  0  done (switch: SWITCHED or RUNNING)
  1  the manager refused or the operation failed (SDO abort, switch result NOT_FOUND/ERROR)
  2  usage or configuration error (bad YAML, overloaded bus, cannot open the bus)
  3  no answer from the manager (not running, wrong --node, --channel or --interface)
"""
from __future__ import annotations

import argparse
import errno
import faulthandler
import importlib.util
import json
import logging
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..audit import AUDIT
from ..cli_args import (
    channel_name,
    did_you_mean,
    flight_seconds,
    node_id,
    positive,
    seconds,
    seconds_or_zero,
    with_clear_hint,
)
from ..errors import BusTaken, ConfigError, NoAnswer, Refused, RocomaError
from ..exit_codes import FAILED, INTERRUPTED, NO_ANSWER, OK, USAGE
from ..fleet import client as fleet_client
from ..fleet.bridge import FleetError
from ..fleet.config import FleetConfig, parse_fleet
from ..live.foxglove import FoxgloveConfig, FoxgloveError, describe_view, parse_address
from ..node.client import ManagerClient
from ..node.objects import (
    ABORT_NOT_FOUND,
    CLEAR,
    ESTOP,
    FAILPROOF_STOP,
    RECOVER,
    RESULT_NAMES,
    SWITCH_REFUSAL,
)
from ..ros2.config import add_ros2_options
from ..ros2.config import from_args as ros2_from_args
from .live import cycle_text
from .main import interrupted_by

if TYPE_CHECKING:  # the client verbs do not import the config (a fast start)
    from ..runtime.config import RuntimeConfig
    from ..runtime.loop import TimingSummary
    from ..runtime.system import Runtime


def _err(message: str) -> None:
    print(f"rocoma-can: {message}", file=sys.stderr, flush=True)


#: ``run``'s console (cli/console.py): its own lines on stdout with the audit trail, its
#: errors on stderr, both in the one format with the time in front
say = logging.getLogger(AUDIT)
log = logging.getLogger(__name__)


# --- run / check-config -----------------------------------------------------------------------

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


def state_dir(*parts: str) -> Path:
    """$XDG_STATE_HOME/rocoma-can/PARTS (~/.local/state/rocoma-can/...): where flight
    records and the demo's recordings go by default."""
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state, "rocoma-can", *parts)


def default_flight_dir() -> Path:
    return state_dir("flight")


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
        from ..ros2.node import describe_node as describe_ros2
        say.info("%s", describe_ros2(runtime.ros2))
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


#: what to do instead of ``run`` on a kernel without SocketCAN
RUN_ELSEWHERE = ("on vcan, from a checkout, tools/vcan-run -- rocoma-can run CONFIG with "
                 "channel: vcan0; without a kernel bus, rocoma-can demo, or interface: "
                 "virtual in CONFIG")
#: what to do instead of a verb that reaches a running manager's bus (status, record ...)
REACH_ELSEWHERE = ("run it where the manager's bus is: the robot's computer, or on vcan, from "
                   "a checkout, inside tools/vcan-run beside the manager")


def no_socketcan_hint(exc: BaseException, instead: str = RUN_ELSEWHERE) -> str:
    """What to do when the kernel has no SocketCAN (EAFNOSUPPORT: containers, WSL, macOS;
    ``instead`` says what), or no such link (ENODEV: a typo, an adapter not plugged in, vcan
    not made), which a new user meets first as an errno: its words say nothing about CAN."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno == errno.EAFNOSUPPORT:
            return f"; this kernel has no SocketCAN (AF_CAN): {instead}"
        if isinstance(seen, OSError) and seen.errno == errno.ENODEV:
            return ("; no such network interface: `ip link` lists them (an adapter plugged "
                    "in, its driver loaded?); rocoma-can doctor CONFIG checks each bus and "
                    "says how to create or raise it")
        seen = seen.__cause__ or seen.__context__
    return ""


def add_foxglove_options(p: argparse.ArgumentParser) -> None:
    """--foxglove and its options, for run and demo alike."""
    g = p.add_argument_group("Foxglove (the live view, extra foxglove)")
    g.add_argument("--foxglove", nargs="?", type=_foxglove_address, default=None,
                   const=_foxglove_address(""), metavar="HOST:PORT",
                   help="serve the live view on a Foxglove WebSocket (127.0.0.1:8765; "
                        "0.0.0.0 serves every interface)")
    g.add_argument("--foxglove-rate", type=positive, default=None, metavar="HZ",
                   help=f"joint states and manager state per second ({FoxgloveConfig.rate:g})")
    g.add_argument("--foxglove-allow-commands", action="store_true",
                   help="accept switch, clear and recover from Foxglove (stops always are)")


def foxglove_from_args(args: argparse.Namespace) -> FoxgloveConfig | None:
    """--foxglove and its options (None: no live view); ValueError for an option of it
    given without it, which would be ignored without a word."""
    if args.foxglove is None:
        given = [option for option, value in (("--foxglove-rate", args.foxglove_rate),
                                              ("--foxglove-allow-commands",
                                               args.foxglove_allow_commands or None))
                 if value is not None]
        if given:
            raise ValueError(f"{' and '.join(given)} without --foxglove: there is no live "
                             "view for it")
        return None
    host, port = args.foxglove
    rate = FoxgloveConfig.rate if args.foxglove_rate is None else args.foxglove_rate
    return FoxgloveConfig(host, port, rate=rate, allow_commands=args.foxglove_allow_commands)


def config_taken_as_address(words: list[str]) -> str:
    """A usage error's hint for ``run --foxglove robot.yaml``: --foxglove's value is
    optional, so it takes the word after it, the config, as its address. Said when that
    word looks like a config (a .yaml or .yml name, or a file that exists), which no
    host is named like."""
    for option, value in zip(words, words[1:]):
        if option == "--foxglove" and (value.lower().endswith((".yaml", ".yml"))
                                       or os.path.isfile(value)):
            return (f"--foxglove took {value!r} as its address: put the config first or "
                    "write --foxglove=HOST:PORT")
    return ""


def _foxglove_address(text: str) -> tuple[str, int]:
    try:
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


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


# --- client commands --------------------------------------------------------------------------

def _client(args: argparse.Namespace, action: Callable[[ManagerClient], int]) -> int:
    from ..drivers.link.bus import open_bus
    try:
        bus = open_bus(args.interface, args.channel, receive_own_messages=False)
    except OSError as exc:
        _err(str(exc) + no_socketcan_hint(exc, REACH_ELSEWHERE))
        return USAGE
    try:
        with ManagerClient(bus, args.node, timeout=args.timeout) as client:
            return action(client)
    except NoAnswer as exc:
        _err(f"{exc} (is rocoma-can run running on {args.interface}:{args.channel}?)")
        return NO_ANSWER
    except (Refused, RocomaError) as exc:  # refused, or not a rocoma-can manager node
        _err(str(exc))
        return FAILED
    finally:
        bus.shutdown()


def _switch(args: argparse.Namespace) -> int:
    """Prints the result (SWITCHED, RUNNING, NOT_FOUND, ERROR) on stdout in every case; a
    refusal's reason (e-stop latched, drives not ready) goes to stderr."""
    if args.zenoh is not None:
        return fleet_client.switch(args)
    def action(client: ManagerClient) -> int:
        try:
            result = client.switch(args.name, timeout=args.wait)
        except Refused as exc:
            if exc.code == ABORT_NOT_FOUND:
                print("NOT_FOUND", flush=True)
                _err(f"no controller {args.name!r}"
                     + did_you_mean(args.name, client.controllers())
                     + " (rocoma-can list names them)")
                return FAILED
            print("ERROR", flush=True)
            _err("switch refused: "
                 + with_clear_hint(client.read_text(SWITCH_REFUSAL) or str(exc)))
            return FAILED
        print(RESULT_NAMES.get(result, str(result)), flush=True)
        if result == 3:
            _err("switch failed: " + with_clear_hint(client.read_text(SWITCH_REFUSAL)
                                                      or "see the manager log"))
        return OK if result in (0, 1) else FAILED
    return _client(args, action)


def _home(args: argparse.Namespace) -> int:
    """Prints how homing ended ("NAME: homed" / "NAME: failed: why"); exit 0 only if homed."""
    def action(client: ManagerClient) -> int:
        result = client.home(args.drive, timeout=args.timeout_homing)
        print(f"{args.drive}: {result}", flush=True)
        return OK if result == "homed" else FAILED
    return _client(args, action)


#: tries of an e-stop or failproof stop over SDO (see _command)
STOP_ATTEMPTS = 3
#: words a stop did not take that its warning names (the rest are counted)
IGNORED_SHOWN = 5
#: characters of each such word it shows
WORD_SHOWN = 40


def _word(word: str) -> str:
    """A command-line word as a warning shows it: ASCII (invalid UTF-8 escaped), cut short."""
    shown = ascii(word[:WORD_SHOWN])
    return shown + (f"... ({len(word)} characters)" if len(word) > WORD_SHOWN else "")


def _command(index: int, verb: str, done: str) -> Callable[[argparse.Namespace], int]:
    through_zenoh = fleet_client.command(verb, done)

    def handler(args: argparse.Namespace) -> int:
        try:
            return sent(args)
        finally:  # a stop is sent first; what it did not take is said after it
            if getattr(args, "ignored", None):
                _err(f"{verb}: ignored (a stop takes nothing but where to send it): "
                     + ", ".join(_word(w) for w in args.ignored[:IGNORED_SHOWN])
                     + (f" and {len(args.ignored) - IGNORED_SHOWN} more"
                        if len(args.ignored) > IGNORED_SHOWN else ""))

    def sent(args: argparse.Namespace) -> int:
        if args.zenoh is not None:
            return through_zenoh(args)
        def action(client: ManagerClient) -> int:
            # The node has one SDO channel: a write takes only its own answer (sdo_write),
            # but one lost on a busy bus goes unanswered. A stop is the same request
            # twice, so it is tried again; the other commands once.
            attempts = STOP_ATTEMPTS if index in (ESTOP, FAILPROOF_STOP) else 1
            for attempt in range(1, attempts + 1):
                try:
                    client.write(index, 1)
                    break
                except (NoAnswer, Refused):
                    if attempt == attempts:
                        raise
            print(done, flush=True)
            return OK
        return _client(args, action)
    return handler


def _status(args: argparse.Namespace) -> int:
    zenoh = args.zenoh is not None
    interval = args.interval if args.interval is not None else (0.5 if zenoh else 1.0)
    low = 0.2 if zenoh else 1.0
    if args.watch and interval < low:  # over SDO each refresh is ~70 frames per drive
        why = ("over Zenoh" if zenoh else "over SDO (each refresh is a block upload on "
               "the drives' bus, ~70 frames per drive)")
        _err(f"status --watch --interval: at least {low:g} s {why}")
        return USAGE

    def show(read: Callable[[], dict[str, Any]], label: str) -> int:
        if args.watch:
            from .live import watch
            return watch(read, label, interval=interval, duration=args.duration)
        status = read()
        if args.json:
            print(json.dumps(status, indent=2), flush=True)
            return OK
        for line in status_lines(status):
            print(line, flush=True)
        return OK
    if zenoh:
        return fleet_client.with_client(
            args, lambda client: show(client.status, f"Zenoh {client.prefix}"))
    return _client(args, lambda client: show(client.status, f"manager node {args.node}"))


def status_lines(status: dict[str, Any]) -> list[str]:
    """``status`` as text, one fact per line (what scripts grep)."""
    status = dict(status)
    drives, buses, cycle = status.pop("drives"), status.pop("buses"), status.pop("cycle")
    fleet = status.pop("zenoh", None)
    status.pop("controllers", None)  # `list` prints them
    lines = []
    for key, value in status.items():
        if key == "estop_cob_id":
            value = f"{value:#05x}"
        elif value in ("", None) and key in ("switch_refused", "estop_cause", "bus_fault"):
            value = "none"
        lines.append(f"{key}: {value}")
    if cycle:
        lines.append(f"cycle: {cycle_text(cycle)}")
    if fleet:
        lines.append("zenoh: " + (f"unavailable: {fleet['error']}" if "error" in fleet else
                                  f"{fleet['prefix']}, alive {fleet['alive']}, queries "
                                  f"{fleet['queries']} ({fleet['refused']} refused), "
                                  f"published {fleet['published']}, errors {fleet['errors']}"))
    for b in buses:
        load = "n/a (in-process)" if b.get("load") is None else f"{b['load']:.0%}"
        lines.append(f"bus {b['name']} ({b['channel']}): planned load {load}, tx errors "
                     f"{b['tx_errors']}, error frames {b['error_frames']}"
                     f"{', fault: ' + b['fault'] if b.get('fault') else ''}")
    for d in drives:
        age = d.get("heartbeat_age")
        lines.append(
            f"drive {d['name']} (node {d['node_id']}): {d['phase']}, {d['cia402_state']}"
            f"{', enabled' if d['enabled'] else ''}, NMT {d['nmt_state']}, heartbeat "
            f"{'never' if age is None else f'{age:.2f} s ago'}"
            + "".join(f", {k} {d[k]:+.4f}" for k in ("position", "velocity", "torque")
                      if d.get(k) is not None)
            + (f", fault: {d['fault']}" if d['fault'] else "")
            + (f", homing: {d['homing']}" if d.get('homing') else ""))
    return lines


def _list(args: argparse.Namespace) -> int:
    if args.zenoh is not None:
        return fleet_client.controllers(args)
    def action(client: ManagerClient) -> int:
        for i, name in enumerate(client.controllers(), 1):
            print(f"{i} {name}", flush=True)
        return OK
    return _client(args, action)


def _bus_options(p: argparse.ArgumentParser, zenoh: bool = True) -> None:
    p.add_argument("-c", "--config", default=None, metavar="CONFIG",
                   help="reach the manager this config runs: its bus's interface and "
                        "channel, its manager node id" + (" and Zenoh prefix" if zenoh else "")
                   + " (the options below override it)")
    p.add_argument("--interface", default=None, help="python-can interface (socketcan)")
    p.add_argument("--channel", type=channel_name, default=None, help="CAN channel (can0)")
    p.add_argument("--node", type=node_id, default=None, help="the manager's node id (100)")
    p.add_argument("--timeout", type=seconds, default=0.5, help="SDO answer timeout, s (0.5)")
    if zenoh:
        fleet_client.add_options(p)


#: where the operator verbs look for the manager without --config or an option
DEFAULT_REACH = {"interface": "socketcan", "channel": "can0", "node": 100}


def operator_verb(handler: Callable[[argparse.Namespace], int]
                  ) -> Callable[[argparse.Namespace], int]:
    """``handler`` with its bus, channel and node id (and Zenoh prefix) resolved: each
    option given, else the config's (``-c CONFIG``), else DEFAULT_REACH. A config that
    cannot be read is a usage error in one line per problem."""
    def resolved(args: argparse.Namespace) -> int:
        reach: dict[str, Any] = dict(DEFAULT_REACH)
        if args.config is not None:
            from ..runtime.config import load_reach
            try:
                found = load_reach(args.config)
            except ConfigError as exc:
                for problem in exc.problems:
                    _err(problem)
                return USAGE
            reach = {"interface": found.interface, "channel": found.channel,
                     "node": found.node_id}
            if getattr(args, "zenoh", None) == "" and found.zenoh_prefix:
                args.zenoh = found.zenoh_prefix  # --zenoh without a prefix: the config's
        for key, value in reach.items():
            if getattr(args, key) is None:
                setattr(args, key, value)
        return handler(args)
    return resolved


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

    p = subparsers.add_parser("switch", help="switch the running manager's controller")
    p.add_argument("name", help="controller name, or its number from rocoma-can list")
    p.add_argument("--wait", type=seconds_or_zero, default=10.0, help="wait for the result, s (10)")
    _bus_options(p)
    p.set_defaults(func=operator_verb(_switch))
    for name, index, text, done in (
            ("estop", ESTOP, "emergency stop (emergency controller, else torque-off)",
             "e-stop requested"),
            ("failproof", FAILPROOF_STOP, "failproof stop (torque-off)", "failproof requested"),
            ("clear", CLEAR, "clear a latched e-stop", "clear requested"),
            ("recover", RECOVER, "fault-reset / restart faulted drives", "recovery started")):
        p = subparsers.add_parser(name, help=text)
        _bus_options(p)
        # a stop acts whatever else the line carries (rocoma_can/stop_surfaces.py: CLI)
        p.set_defaults(func=operator_verb(_command(index, name, done)),
                       takes_anything=index in (ESTOP, FAILPROOF_STOP))
    p = subparsers.add_parser(
        "home", help="home one drive (CiA 402 homing, its own method) while the active "
                     "controller holds the others; waits for the result")
    p.add_argument("drive", help="the drive's name in the config")
    p.add_argument("--timeout-homing", type=seconds, default=90.0, metavar="S",
                   help="give up waiting after S seconds (90; the manager's own limit is "
                        "the drive's homing_timeout)")
    _bus_options(p, zenoh=False)
    p.set_defaults(func=operator_verb(_home))
    p = subparsers.add_parser("status", help="state, active controller, e-stop latch and cause, "
                                              "every drive's bring-up, CiA 402 state and fault")
    p.add_argument("--json", action="store_true", help="everything as one JSON document")
    p.add_argument("--watch", action="store_true",
                   help="a live view, refreshed until Ctrl-C (needs rocoma-can[live])")
    p.add_argument("--interval", type=seconds, default=None, metavar="S",
                   help="--watch: seconds between refreshes (1 over SDO, at least 1: each "
                        "is a block upload on the drives' bus; 0.5 over Zenoh)")
    p.add_argument("--duration", type=seconds, default=None, metavar="S",
                   help="--watch: stop after S seconds (default: Ctrl-C)")
    _bus_options(p)
    p.set_defaults(func=operator_verb(_status))
    p = subparsers.add_parser("list", help="the switchable controllers, numbered")
    _bus_options(p)
    p.set_defaults(func=operator_verb(_list))
