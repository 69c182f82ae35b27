"""``rocoma-can doctor [CONFIG]``: is this host ready for the configuration, as a checklist
with the fix for each miss. It only reads (sysfs, iproute2, rlimits, one SCHED_FIFO probe
on a thread that ends at once; with CONFIG it listens on its buses, sending nothing, for
another manager, as run does before it starts); every fix is printed, never run.
``--timing`` also runs the bare control loop (runtime/host_timing.py) for a few seconds at
the rate: whether this host keeps a loop's speed, which no setting read from /sys tells.

Exit codes: 0 nothing blocks the configuration (warnings allowed), 1 something does (a
link missing, down, at another bit rate or bus-off; a realtime priority that is refused;
another manager heard on a bus),
2 usage or a configuration that does not load.
"""
from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from typing import TYPE_CHECKING

from ..errors import ConfigError
from .args import channel_name, positive, seconds
from .console import err
from .exit_codes import FAILED, OK, USAGE

if TYPE_CHECKING:  # the checks load on use: ``rocoma-can --help`` stays quick
    from ..drivers.plan.config import BusConfig
    from ..runtime.host import Check

_MARK = {"ok": "ok", "warn": "WARN", "fail": "FAIL", "n/a": "n/a"}
#: --timing: seconds when given without a number (more where the rate needs them for
#: host_timing.MIN_CYCLES a check), the rate without CONFIG or --rate, and the longest run
#: accepted (at a configured SCHED_FIFO priority the bare loop takes its CPU as the real
#: loop would, the whole time if the host is slow)
DEFAULT_TIMING_SECONDS = 10.0
DEFAULT_TIMING_RATE = 1000.0
MAX_TIMING_SECONDS = 120.0
AUTO = 0.0  # --timing without SECONDS (not a string: argparse would convert it)



def _link_checks(channels: Sequence[tuple[str, BusConfig | None]]) -> list[Check]:
    """Each (channel, its bus in the config or None) as a link of this host."""
    from ..drivers.link.can_link import read_link
    from ..runtime.can_checks import Wanted, link_checks
    checks: list[Check] = []
    for channel, bus in channels:
        want = Wanted.of(bus) if bus is not None else Wanted(channel)
        checks += link_checks(read_link(channel), want)
    return checks


def gather(args: argparse.Namespace) -> tuple[str, list[Check]]:
    """(what was checked against, the checks). ConfigError: a config that does not load."""
    subject, checks, (rate, priority, cpus, spin) = _read_checks(args)
    if args.timing is not None:
        from ..runtime.host_timing import timing_checks
        rate = args.rate or rate
        checks += timing_checks(rate, timing_seconds(args.timing, rate), priority, cpus, spin)
    return subject, checks


def timing_seconds(asked: float, rate: float) -> float:
    """--timing's SECONDS (``AUTO``: the default, or enough for MIN_CYCLES a check);
    ValueError saying what would do when they give a check fewer than MIN_CYCLES."""
    from ..runtime.host_timing import MIN_CYCLES
    need = 2 * MIN_CYCLES / rate  # (two checks)
    run = max(DEFAULT_TIMING_SECONDS, need) if asked == AUTO else asked
    if run < need or run > MAX_TIMING_SECONDS:
        raise ValueError(f"--timing {run:g} s at {rate:g} Hz: each of its two checks "
                         f"needs {MIN_CYCLES} cycles, at least {need:g} s, and it runs "
                         f"{MAX_TIMING_SECONDS:g} s at most")
    return run


#: how the config runs its loop: rate, realtime.priority, realtime.cpus, its spin (s)
_LoopRun = tuple[float, "int | None", "set[int] | None", "float | None"]


def _read_checks(args: argparse.Namespace) -> tuple[str, list[Check], _LoopRun]:
    """(subject, the checks that only read, how a timing check runs the loop)."""
    from ..drivers.link.can_link import can_interfaces
    from ..runtime.host import Check, realtime_checks
    if args.config:
        from ..runtime.config import load
        config = load(args.config)
        checks: list[Check] = []
        for bus in config.buses:
            if bus.interface == "socketcan":
                checks += _link_checks([(bus.channel, bus)])
            else:
                checks.append(Check(f"bus {bus.label}", "n/a", f"interface {bus.interface!r}: "
                                    "doctor reads SocketCAN links only"))
        from ..runtime.another_manager import doctor_check
        checks.append(doctor_check(config))  # what run listens for before it sends
        return (args.config, checks + realtime_checks(config.priority, config.cpus, True),
                (config.rate, config.priority, config.cpus, config.spin))
    if args.channel:
        checks = _link_checks([(args.channel, None)])
        subject = f"{args.channel} (no config: bit rates shown, not compared)"
    else:
        found = can_interfaces()
        checks = _link_checks([(name, None) for name in found])
        subject = (f"CAN interfaces {', '.join(found)} (no config: bit rates shown, not "
                   "compared)" if found else "this host (no config)")
        if not found:
            checks.append(Check("CAN interfaces", "warn", "none in /sys/class/net (no link of "
                                "type 280, ARPHRD_CAN)", "connect the adapter or load its "
                                "driver; for a bench: sudo modprobe vcan && sudo ip link add "
                                "dev vcan0 type vcan && sudo ip link set vcan0 up"))
    checks += realtime_checks(None, None, False)
    checks.append(Check("configuration", "n/a", "no CONFIG: the bit rates, CAN FD and "
                        "realtime.priority/cpus it asks for were not judged",
                        "rocoma-can doctor CONFIG"))
    return subject, checks, (DEFAULT_TIMING_RATE, None, None, None)


def _print(subject: str, checks: Sequence[Check]) -> None:
    width = max(len(c.name) for c in checks)
    print(f"doctor: {subject}", flush=True)
    for c in checks:
        print(f"  {_MARK[c.status]:<4}  {c.name:<{width}}  {c.found}", flush=True)
        if c.fix and c.status in ("warn", "fail"):
            print(f"        {'':<{width}}  fix: {c.fix}", flush=True)
    fails = sum(c.status == "fail" for c in checks)
    warns = sum(c.status == "warn" for c in checks)
    verdict = "blocks it" if fails else "nothing blocks it"
    print(f"{fails} failed, {warns} warnings: {verdict}", flush=True)


def _doctor(args: argparse.Namespace) -> int:
    if args.config and (args.channel or args.interface):
        err("doctor: give CONFIG or --channel, not both (the config names its buses)")
        return USAGE
    if args.interface and not args.channel:
        err("doctor: --interface needs --channel")
        return USAGE
    if args.interface not in (None, "socketcan"):
        err(f"doctor: --interface {args.interface!r}: doctor reads SocketCAN links only")
        return USAGE
    from ..runtime.config_check import MAX_RATE
    if args.rate is not None and not (args.rate <= MAX_RATE and args.timing is not None):
        err(f"doctor: --rate {args.rate:g}: give 0 < HZ <= {MAX_RATE}, with --timing")
        return USAGE
    try:
        subject, checks = gather(args)
    except ConfigError as exc:
        for problem in exc.problems:
            err(problem)
        return USAGE
    except ValueError as exc:  # --timing's seconds against the rate (timing_seconds)
        err(f"doctor: {exc}")
        return USAGE
    if args.json:
        print(json.dumps([c.as_dict() for c in checks], indent=2), flush=True)
    else:
        _print(subject, checks)
    return FAILED if any(c.status == "fail" for c in checks) else OK


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "doctor", help="is this host ready for CONFIG: CAN links, real-time rights, CPUs; "
                       "the fix for each miss",
        description="A checklist of the host, read only: each configured SocketCAN link "
                    "(exists, up, bit rate and CAN FD as configured, ERROR-ACTIVE, error "
                    "counters, txqueuelen, restart-ms), the PREEMPT_RT kernel, SCHED_FIFO "
                    "at realtime.priority, mlockall, the CPU governor and isolated CPUs; "
                    "with --timing, the bare control loop measured for a few seconds. "
                    "Without CONFIG: every CAN link of the host, or --channel. Exit 0: "
                    "nothing blocks the config (warnings allowed); 1: something does; 2: "
                    "usage, or a config that does not load.")
    p.add_argument("config", nargs="?", default=None, help="the run's YAML (optional)")
    p.add_argument("--channel", type=channel_name, default=None,
                   help="without CONFIG: check this link only")
    p.add_argument("--interface", default=None,
                   help="without CONFIG: python-can interface of --channel (socketcan)")
    p.add_argument("--json", action="store_true",
                   help="a JSON list of {name, status, found, fix}")
    p.add_argument("--timing", type=seconds, nargs="?", const=AUTO,
                   default=None, metavar="SECONDS",
                   help="also run the bare control loop for SECONDS (default "
                        f"{DEFAULT_TIMING_SECONDS:g}, or what 1000 cycles a check take at a "
                        f"low rate; at most {MAX_TIMING_SECONDS:g}) at the config's rate, "
                        "priority and CPUs, with 40 %% of the period as Python work, in the "
                        "CPU's cache and over 4 MiB: does this host keep a loop's speed "
                        "(warns above 0.1 %% overruns, or a work whose slowest cycles take "
                        "over twice its median)")
    p.add_argument("--rate", type=positive, default=None, metavar="HZ",
                   help="--timing's rate instead of the config's "
                        f"({DEFAULT_TIMING_RATE:g} without CONFIG)")
    p.set_defaults(func=_doctor)
