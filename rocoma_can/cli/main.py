"""The ``rocoma-can`` command. Each group of sub-commands is a module of cli/ (COMMAND_MODULES)
and registers itself here through a ``register(subparsers)`` function returning nothing; the
handler is stored with ``parser.set_defaults(func=handler)`` and returns an exit code. Each
sub-command's parser is a CommandParser (``add_parser(..., hint=...)``); ``set_defaults(
clock=True, audit=True)`` gives a verb ``run``'s console (console.py)."""
from __future__ import annotations

import argparse
import importlib
import re
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any, NoReturn

from .. import __version__
from ..spelling import did_you_mean
from .console import console, err, point_stdout_at_devnull, stdout_gone
from .exit_codes import INTERRUPTED, OK, PIPE_CLOSED, USAGE

# Modules that contribute sub-commands, in help order.
COMMAND_MODULES: tuple[str, ...] = (
    "rocoma_can.cli.demo.command",
    "rocoma_can.cli.run",
    "rocoma_can.cli.operator_verbs",
    "rocoma_can.cli.scan",
    "rocoma_can.cli.init_config",
    "rocoma_can.cli.doctor",
    "rocoma_can.cli.record",
    "rocoma_can.cli.fleet",
    "rocoma_can.cli.scaffold",
    "rocoma_can.cli.sim",
)


def plain(text: str) -> str:
    """Help text as a terminal shows it: the docstrings and help strings the verbs share
    with the docs mark code with reStructuredText/Markdown backticks, which --help
    printed as they are (````rocoma-can sim````)."""
    return text.replace("``", "").replace("`", "")


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

    def format_help(self) -> str:
        return plain(super().format_help())


def verbs_of(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The top parser's verbs, each with its parser."""
    return next(a.choices for a in parser._actions
                if isinstance(a, argparse._SubParsersAction))


class TopParser(argparse.ArgumentParser):
    """The ``rocoma-can`` parser: an unknown verb gets the nearest one as a hint
    (``rocoma-can stauts``: did you mean 'status'?)."""

    def error(self, message: str) -> NoReturn:
        unknown = re.match(r"argument COMMAND: invalid choice: '([^']*)'", message)
        if unknown is not None:
            message = f"unknown command {unknown.group(1)!r}" \
                + did_you_mean(unknown.group(1), verbs_of(self)) \
                + " (rocoma-can --help lists them)"
        super().error(message)

    def format_help(self) -> str:
        return plain(super().format_help())


def _option_hint(parser: argparse.ArgumentParser, verb: str | None,
                 extra: Sequence[str]) -> str:
    """The nearest option of the verb to the first unknown one (``--channle``: ", did you
    mean '--channel'?"), as an unknown verb gets; "" when none is near."""
    typed = next((word.split("=", 1)[0] for word in extra if word.startswith("--")), None)
    command = verbs_of(parser).get(verb) if verb else None
    if typed is None or command is None:
        return ""
    return did_you_mean(typed, [option for action in command._actions
                                for option in action.option_strings if option.startswith("--")])


VERBOSE_HELP = "more log output (-vv for debug), before or after the command"


def build_parser() -> argparse.ArgumentParser:
    parser = TopParser(
        prog="rocoma-can",
        description="Robot controller manager for CANopen CiA 402 actuator buses.")
    parser.add_argument("--version", action="version", version=f"rocoma-can {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help=VERBOSE_HELP)
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND",
                                       parser_class=CommandParser)
    for module in COMMAND_MODULES:
        importlib.import_module(module).register(subparsers)
    for verb in subparsers.choices.values():  # `rocoma-can status -v` as `rocoma-can -v status`
        verb.add_argument("-v", "--verbose", action="count", default=0, dest="verbose_after",
                          help=VERBOSE_HELP)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``rocoma-can`` command on ``argv`` (default: the process's arguments) and return
    its exit code (``exit_codes.py``); ``python -m rocoma_can`` and the console script call it."""
    restore = stop_signals_interrupt()
    args: argparse.Namespace | None = None
    try:  # (the sub-commands' imports too: a Ctrl-C at once is no traceback)
        parser = build_parser()
        try:
            args, extra = parser.parse_known_args(argv)
            if extra and not getattr(args, "takes_anything", False):
                parser.error(f"unrecognized arguments: {' '.join(extra)}"
                             + _option_hint(parser, args.command, extra))
        except SystemExit as exc:  # --help, --version (a usage error: its line on stderr)
            sys.stdout.flush()
            if exc.code in (0, None) and stdout_gone():  # (argparse drops its failed
                raise BrokenPipeError from None        # write without a word)
            raise
        args.ignored = extra  # a stop's: it acts whatever else the line carries
        verbose = args.verbose + getattr(args, "verbose_after", 0)
        with console(verbose, clock=getattr(args, "clock", False),
                     audit=getattr(args, "audit", False)):
            if not getattr(args, "func", None):
                parser.print_help()
                return USAGE
            code = int(args.func(args) or OK)
            sys.stdout.flush()  # (a reader gone is found here, not at the interpreter's exit)
            return code
    except KeyboardInterrupt:  # one the command did not say itself (run says each phase)
        err(f"interrupted ({interrupted_by()})" + (
            " while starting: nothing was sent or changed" if args is None else ""))
        return INTERRUPTED
    except BrokenPipeError:  # `rocoma-can status | head -3`: its reader has gone (console.py)
        if not stdout_gone():
            raise
        point_stdout_at_devnull()
        return PIPE_CLOSED
    finally:
        restore()


_stopped_by = ["SIGINT"]  # the signal of the last interruption (stop_signals_interrupt)


def interrupted_by() -> str:
    """The stop signal that interrupted the command last ("SIGINT" or "SIGTERM")."""
    return _stopped_by[0]


def _interrupt(signum: int, frame: FrameType | None) -> None:
    """Python's own SIGINT handler, for SIGTERM too, saying which signal it was."""
    _stopped_by[0] = signal.Signals(signum).name
    raise KeyboardInterrupt


def stop_signals_interrupt() -> Callable[[], None]:
    """SIGTERM, where nothing else handles it, interrupts as Ctrl-C does (KeyboardInterrupt,
    exit 130): a command's own handlers (the control loop's while it runs) take both, and
    outside them, a stop signal while ``run`` closes (a second one, after the loop's
    torque-off) still closes what it started, the writer process too; by default it ended
    the process at once (exit 143), leaving a writer that did not answer running.

    SIGINT too, when the process started with it ignored: a shell without job control
    starts a background job so (``rocoma-can run robot.yaml &`` in a script, a launcher);
    the loop takes SIGINT anyway, and outside the loop an operator's Ctrl-C or ``kill -INT``
    went unanswered. A stop signal is never ignored here. Each raises KeyboardInterrupt
    and is remembered (``interrupted_by``: ``run`` names it in what it says). Returns what
    puts the previous handlers back (nothing to do off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous: dict[signal.Signals, Any] = {}
    for sig, unhandled in ((signal.SIGTERM, (signal.SIG_DFL,)),
                           (signal.SIGINT, (signal.SIG_IGN, signal.default_int_handler))):
        if signal.getsignal(sig) in unhandled:
            previous[sig] = signal.signal(sig, _interrupt)

    def restore() -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return restore


if __name__ == "__main__":
    sys.exit(main())
