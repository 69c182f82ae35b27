"""The Foxglove live view's options, for ``run`` and ``demo`` alike: ``--foxglove
[HOST:PORT]`` and its rate and commands, read into a FoxgloveConfig, and the usage hint for
a config taken as its address."""
from __future__ import annotations

import argparse
import os

from ..live.foxglove import FoxgloveConfig, parse_address
from .args import positive


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

