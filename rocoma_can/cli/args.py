"""What the commands share on their command lines: argparse types for the numbers they
take (the hints their refusals carry are in hints.py). A value that is not a finite number
in its range is a usage error naming the option (argparse prints it and exits 2), never a
traceback, a busy loop (``Event.wait(nan)`` returns at once) or a run without end
(``--duration nan``)."""
from __future__ import annotations

import argparse
import math

#: the longest duration or timeout a command line may ask for (a year)
LONGEST = 365 * 24 * 3600.0
#: the longest flight-recorder window (10 min: 600,000 cycles at 1 kHz)
MAX_FLIGHT_SECONDS = 600.0


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _int(text: str) -> int:
    """Decimal ("010" is 10, as int() reads it), or 0x/0o/0b prefixed."""
    prefixed = text.strip().lower().lstrip("+-").startswith(("0x", "0o", "0b"))
    return int(text, 0) if prefixed else int(text)


def seconds(text: str) -> float:
    """A duration or timeout: 0 < s <= a year."""
    value = _finite(text)
    if not 0 < value <= LONGEST:
        raise argparse.ArgumentTypeError(f"expected seconds > 0 (at most {LONGEST:.0f}), "
                                         f"got {text!r}")
    return value


def flight_seconds(text: str) -> float:
    """The flight recorder's window: its ring holds rate x seconds cycles in memory, so a
    window of hours would take gigabytes before the first e-stop."""
    value = _finite(text)
    if not 0 < value <= MAX_FLIGHT_SECONDS:
        raise argparse.ArgumentTypeError(f"expected seconds, 0 < s <= {MAX_FLIGHT_SECONDS:.0f}, "
                                         f"got {text!r}")
    return value


def seconds_or_zero(text: str) -> float:
    """A delay or an interval where 0 means "none": 0 <= s <= a year."""
    value = _finite(text)
    if not 0 <= value <= LONGEST:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0 (at most {LONGEST:.0f}), "
                                         f"got {text!r}")
    return value


def positive(text: str) -> float:
    """A physical quantity that must be > 0 (a rate, a torque)."""
    value = _finite(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def _whole(text: str, lo: int, hi: int | None, expected: str) -> int:
    """A whole number in lo..hi (hi None: no upper bound); ``expected`` names the range."""
    try:
        value = _int(text)
    except ValueError:
        value = None
    if value is None or value < lo or (hi is not None and value > hi):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def count(text: str) -> int:
    """A whole number >= 1 (increments per revolution, drives)."""
    return _whole(text, 1, None, "a whole number >= 1")


def rt_priority(text: str) -> int:
    """A SCHED_FIFO priority, 1..99 (a config's ``realtime.priority``)."""
    return _whole(text, 1, 99, "a real-time priority 1..99")


def node_id(text: str) -> int:
    """A CANopen node id, 1..127."""
    return _whole(text, 1, 127, "a node id 1..127")


def channel_name(text: str) -> str:
    """A CAN channel's name, never empty: ``--channel "$CH"`` with CH unset would otherwise
    mean the verb's default link, or for ``doctor`` every link, and say nothing."""
    if not text.strip():
        raise argparse.ArgumentTypeError(
            f"expected a CAN channel (can0, vcan0, a number for Kvaser, IXXAT, Vector), "
            f"got {text!r}")
    return text
