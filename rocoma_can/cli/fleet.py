"""``rocoma-can fleet`` (every manager alive on Zenoh, with its state) and the operator
verbs' ``--zenoh`` path: ``switch``, ``list``, the stops and ``status`` through a manager's
Zenoh queries (fleet/client.py's FleetClient) instead of its CANopen node. The exit codes
mean what they mean over SDO (cli/operator_verbs.py)."""
from __future__ import annotations

import argparse
from collections.abc import Callable

from ..errors import NoAnswer, RocomaError
from ..fleet.bridge import FleetError
from ..fleet.client import FleetClient
from ..spelling import did_you_mean
from .args import seconds
from .console import err
from .exit_codes import FAILED, NO_ANSWER, OK, USAGE
from .hints import with_clear_hint


def add_zenoh_options(p: argparse.ArgumentParser, prefix: bool = True) -> None:
    """``--zenoh [PREFIX]`` (``prefix``) and how to reach Zenoh, for every bus verb."""
    if prefix:
        p.add_argument("--zenoh", nargs="?", const="", default=None, metavar="PREFIX",
                       help="act through Zenoh instead of SDO (default prefix: "
                            "rocoma/<host>)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 "
                        "(repeatable; default: multicast scouting)")
    p.add_argument("--zenoh-no-multicast", action="store_true",
                   help="no multicast scouting (connect only to --zenoh-connect)")


def with_client(args: argparse.Namespace, action: Callable[[FleetClient], int]) -> int:
    try:
        client = FleetClient(args.zenoh or "", args.zenoh_connect,
                             multicast=False if args.zenoh_no_multicast else None,
                             timeout=max(args.timeout, 3.0))
    except FleetError as exc:
        err(str(exc))
        return USAGE
    try:
        return action(client)
    except NoAnswer as exc:
        err(str(exc))
        return NO_ANSWER
    except RocomaError as exc:
        err(str(exc))
        return FAILED
    finally:
        client.close()


def switch(args: argparse.Namespace) -> int:
    def action(client: FleetClient) -> int:
        answer = client.query("switch", args.name, timeout=args.wait)
        result = answer.get("result", "ERROR")
        print(result, flush=True)
        if answer.get("error"):
            hint = did_you_mean(args.name, client.status().get("controllers", [])) \
                if result == "NOT_FOUND" else ""
            err(with_clear_hint(answer["error"]) + hint)
        return OK if result in ("SWITCHED", "RUNNING") else FAILED
    return with_client(args, action)


def command(verb: str, done: str) -> Callable[[argparse.Namespace], int]:
    def handler(args: argparse.Namespace) -> int:
        def action(client: FleetClient) -> int:
            answer = client.query(verb)
            if not answer.get("ok"):
                err(f"{verb} refused: {answer.get('error', 'no reason given')}")
                return FAILED
            print(done, flush=True)
            return OK
        return with_client(args, action)
    return handler


def controllers(args: argparse.Namespace) -> int:
    def action(client: FleetClient) -> int:
        for i, name in enumerate(client.status().get("controllers", []), 1):
            print(f"{i} {name}", flush=True)
        return OK
    return with_client(args, action)


def fleet(args: argparse.Namespace) -> int:
    """Every manager alive on the network, with its state."""
    def action(client: FleetClient) -> int:
        prefixes = client.alive(timeout=args.wait)
        if not prefixes:
            print("no manager alive on Zenoh", flush=True)
            return OK
        for prefix in prefixes:
            client.prefix = prefix
            try:
                s = client.status()
            except NoAnswer:
                print(f"{prefix}: alive, no status answer", flush=True)
                continue
            print(f"{prefix}: {s['state']}, {s.get('active', '?')}"
                  f"{', e-stop latched' if s.get('latched') else ''}"
                  f"{', last e-stop: ' + s['estop_cause'] if s.get('estop_cause') else ''}"
                  f", {len(s.get('drives', []))} drives", flush=True)
        return OK
    return with_client(args, action)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("fleet", help="every manager alive on Zenoh, with its state")
    p.add_argument("--wait", type=seconds, default=2.0, metavar="S",
                   help="how long to look for managers (2)")
    p.add_argument("--timeout", type=seconds, default=3.0, help="status answer timeout, s (3)")
    add_zenoh_options(p, prefix=False)
    p.set_defaults(func=fleet, zenoh="")
