"""The ``rocoma-can`` command. Each sub-command lives next to the code it drives and
registers itself here through a ``register(subparsers)`` function returning nothing; the
handler is stored with ``parser.set_defaults(func=handler)`` and returns an exit code. Each
sub-command's parser is a CommandParser (``add_parser(..., hint=...)``)."""
from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from ..exit_codes import INTERRUPTED, OK, USAGE

# Modules that contribute sub-commands, in help order.
COMMAND_MODULES: tuple[str, ...] = (
    "rocoma_can.cli.demo",
    "rocoma_can.cli.commands",
    "rocoma_can.cli.scan",
    "rocoma_can.cli.init_config",
    "rocoma_can.cli.doctor",
    "rocoma_can.cli.record",
    "rocoma_can.fleet.client",
    "rocoma_can.cli.scaffold",
    "rocoma_can.drivers.sim.cli",
)


class CommandParser(argparse.ArgumentParser):
    """A sub-command's parser, which may add a hint to a usage error: argparse says what is
    missing, not why (``run --foxglove robot.yaml``: --foxglove, whose value is optional,
    took the config as its address, and "required: config" is all it says). ``hint``, a
    keyword of ``add_parser``: the command line's words -> a hint ("" for none)."""

    def __init__(self, *args: Any, hint: Callable[[list[str]], str] | None = None,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._hint = hint
        self._words: list[str] = []

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        self._words = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        hint = self._hint(self._words) if self._hint is not None else ""
        super().error(f"{message}; {hint}" if hint else message)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rocoma-can",
        description="Robot controller manager for CANopen CiA 402 actuator buses.")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND",
                                       parser_class=CommandParser)
    for module in COMMAND_MODULES:
        importlib.import_module(module).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    restore = stop_signals_interrupt()
    try:  # (the sub-commands' imports too: a Ctrl-C at once is no traceback)
        parser = build_parser()
        args = parser.parse_args(argv)
        level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
        logging.basicConfig(level=level,
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        if args.verbose < 2:
            for logger in SAID_BY_US:
                logging.getLogger(logger).addFilter(_said_by_us)
        if not getattr(args, "func", None):
            parser.print_help()
            return USAGE
        return int(args.func(args) or OK)
    except KeyboardInterrupt:
        return INTERRUPTED
    finally:
        restore()


#: library log lines a command says itself, better: logger -> how the line begins.
#: canopen's SDO client logs an ERROR line each time a request times out (a drive not
#: answering, once per try); the command says what failed once, naming the drive and what
#: to check. python-can's socketcan logs one for a link it cannot open, then raises; the
#: command says it with the bus's name and what to do. Shown with -vv.
SAID_BY_US = {"canopen.sdo.client": "Transfer aborted by client",
              "can.interfaces.socketcan.socketcan": "Could not access SocketCAN device"}


def _said_by_us(record: logging.LogRecord) -> bool:
    return not record.getMessage().startswith(SAID_BY_US.get(record.name, "\0"))


def stop_signals_interrupt() -> Callable[[], None]:
    """SIGTERM, where nothing else handles it, interrupts as Ctrl-C does (KeyboardInterrupt,
    exit 130): a command's own handlers (the control loop's while it runs) take both, and
    outside them, a stop signal while ``run`` closes (a second one, after the loop's
    torque-off) still closes what it started, the writer process too; by default it ended
    the process at once (exit 143), leaving a writer that did not answer running.

    SIGINT too, when the process started with it ignored: a shell without job control
    starts a background job so (``rocoma-can run robot.yaml &`` in a script, a launcher);
    the loop takes SIGINT anyway, and outside the loop an operator's Ctrl-C or ``kill -INT``
    went unanswered. A stop signal is never ignored here. Returns what puts the previous
    handlers back (nothing to do off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous: dict[signal.Signals, Any] = {}
    for sig, unhandled in ((signal.SIGTERM, signal.SIG_DFL), (signal.SIGINT, signal.SIG_IGN)):
        if signal.getsignal(sig) == unhandled:
            previous[sig] = signal.signal(sig, signal.default_int_handler)

    def restore() -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return restore


if __name__ == "__main__":
    sys.exit(main())
