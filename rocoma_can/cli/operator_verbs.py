"""The operator verbs, which talk to a running manager over its bus (its CANopen node's
SDO objects) or, with ``--zenoh``, over Zenoh (cli/fleet.py): ``switch``, ``estop``,
``failproof``, ``clear``, ``recover``, ``home``, ``status``, ``list``.

Exit codes (for shell scripts):
  0  done (switch: SWITCHED or RUNNING)
  1  the manager refused or the operation failed (SDO abort, switch result NOT_FOUND/ERROR)
  2  usage or configuration error (a config that cannot be read, cannot open the bus)
  3  no answer from the manager (not running, wrong --node, --channel or --interface)
"""
from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

from ..errors import ConfigError, NoAnswer, Refused, RocomaError
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
from ..spelling import did_you_mean
from . import fleet
from .args import channel_name, node_id, seconds, seconds_or_zero
from .console import err
from .exit_codes import FAILED, NO_ANSWER, OK, USAGE
from .hints import REACH_ELSEWHERE, no_socketcan_hint, with_clear_hint
from .status_watch import cycle_text


def _client(args: argparse.Namespace, action: Callable[[ManagerClient], int]) -> int:
    from ..drivers.link.bus import open_bus
    try:
        bus = open_bus(args.interface, args.channel, receive_own_messages=False)
    except OSError as exc:
        err(str(exc) + no_socketcan_hint(exc, REACH_ELSEWHERE))
        return USAGE
    try:
        with ManagerClient(bus, args.node, timeout=args.timeout) as client:
            return action(client)
    except NoAnswer as exc:
        err(f"{exc} (is rocoma-can run running on {args.interface}:{args.channel}?)")
        return NO_ANSWER
    except (Refused, RocomaError) as exc:  # refused, or not a rocoma-can manager node
        err(str(exc))
        return FAILED
    finally:
        bus.shutdown()


def _switch(args: argparse.Namespace) -> int:
    """Prints the result (SWITCHED, RUNNING, NOT_FOUND, ERROR) on stdout in every case; a
    refusal's reason (e-stop latched, drives not ready) goes to stderr."""
    if args.zenoh is not None:
        return fleet.switch(args)
    def action(client: ManagerClient) -> int:
        try:
            result = client.switch(args.name, timeout=args.wait)
        except Refused as exc:
            if exc.code == ABORT_NOT_FOUND:
                print("NOT_FOUND", flush=True)
                err(f"no controller {args.name!r}"
                    + did_you_mean(args.name, client.controllers())
                    + " (rocoma-can list names them)")
                return FAILED
            print("ERROR", flush=True)
            err("switch refused: "
                + with_clear_hint(client.read_text(SWITCH_REFUSAL) or str(exc)))
            return FAILED
        print(RESULT_NAMES.get(result, str(result)), flush=True)
        if result == 3:
            err("switch failed: " + with_clear_hint(client.read_text(SWITCH_REFUSAL)
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
    through_zenoh = fleet.command(verb, done)

    def handler(args: argparse.Namespace) -> int:
        try:
            return sent(args)
        finally:  # a stop is sent first; what it did not take is said after it
            if getattr(args, "ignored", None):
                err(f"{verb}: ignored (a stop takes nothing but where to send it): "
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
        err(f"status --watch --interval: at least {low:g} s {why}")
        return USAGE

    def show(read: Callable[[], dict[str, Any]], label: str) -> int:
        if args.watch:
            from .status_watch import watch
            return watch(read, label, interval=interval, duration=args.duration)
        status = read()
        if args.json:
            print(json.dumps(status, indent=2), flush=True)
            return OK
        for line in status_lines(status):
            print(line, flush=True)
        return OK
    if zenoh:
        return fleet.with_client(
            args, lambda client: show(client.status, f"Zenoh {client.prefix}"))
    return _client(args, lambda client: show(client.status, f"manager node {args.node}"))


def status_lines(status: dict[str, Any]) -> list[str]:
    """``status`` as text, one fact per line (what scripts grep)."""
    status = dict(status)
    drives, buses, cycle = status.pop("drives"), status.pop("buses"), status.pop("cycle")
    zenoh = status.pop("zenoh", None)
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
    if zenoh:
        lines.append("zenoh: " + (f"unavailable: {zenoh['error']}" if "error" in zenoh else
                                  f"{zenoh['prefix']}, alive {zenoh['alive']}, queries "
                                  f"{zenoh['queries']} ({zenoh['refused']} refused), "
                                  f"published {zenoh['published']}, errors {zenoh['errors']}"))
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
        return fleet.controllers(args)
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
        fleet.add_zenoh_options(p)


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
                    err(problem)
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
