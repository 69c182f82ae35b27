"""The ``rocoma-can`` command. Each sub-command lives next to the code it drives and
registers itself here through a ``register(subparsers)`` function returning nothing; the
handler is stored with ``parser.set_defaults(func=handler)`` and returns an exit code."""
from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from ..exit_codes import INTERRUPTED, OK, USAGE

# Modules that contribute sub-commands, in help order.
COMMAND_MODULES: tuple[str, ...] = (
    "rocoma_can.cli.demo",
    "rocoma_can.cli.commands",
    "rocoma_can.cli.doctor",
    "rocoma_can.cli.record",
    "rocoma_can.fleet.client",
    "rocoma_can.cli.scaffold",
    "rocoma_can.drivers.sim.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rocoma-can",
        description="Robot controller manager for CANopen CiA 402 actuator buses.")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in COMMAND_MODULES:
        importlib.import_module(module).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return USAGE
    try:
        return int(args.func(args) or OK)
    except KeyboardInterrupt:
        return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
