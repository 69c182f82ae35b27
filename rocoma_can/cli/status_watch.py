"""``rocoma-can status --watch``: a live view of a running manager, from any machine on its
bus, refreshed a few times a second (rich, the optional extra ``rocoma-can[live]``).

It asks what ``status`` asks, over SDO (the manager node serves it), or with ``--zenoh``
the manager's Zenoh status query (nothing in the control loop waits for either): the
manager's state and active controller, the e-stop latch and cause, each bus's planned load
and errors, the loop's cycle statistics, and per drive its bring-up
phase, CiA 402 state, NMT state, heartbeat age, feedback, fault and homing. Bring-up shows
as progress bars (the drives' phases towards READY); a recovery and a homing, which have no
known length, pulse. A manager that stops answering stays on screen, marked as stale, and
the view goes on asking.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ..errors import RocomaError
from .console import err
from .exit_codes import OK, USAGE

if TYPE_CHECKING:
    from rich.console import Console, RenderableType


#: bring-up phases in order (bringup/drive_bringup.BringupPhase); READY is the end of the bar
PHASES = ("WAIT_BOOT", "CONFIGURING", "STARTING", "RESETTING", "PROBING", "READY")
STATE_STYLES = {"OK": "bold white on green", "EMERGENCY": "bold black on dark_orange",
                "FAILPROOF": "bold white on red"}
CIA402_STYLES = {"OPERATION_ENABLED": "green", "FAULT": "bold red",
                 "FAULT_REACTION_ACTIVE": "bold red", "QUICK_STOP_ACTIVE": "dark_orange"}


def watch(read: Callable[[], dict[str, Any]], label: str, interval: float = 0.5,
          duration: float | None = None, console: Console | None = None,
          stop: threading.Event | None = None) -> int:
    """Show ``read()`` (a status document: ManagerClient.status over SDO, or the Zenoh
    status query) until Ctrl-C, ``duration`` s or ``stop``; ``label`` names the manager.
    Exit code (2: rich missing)."""
    try:
        from rich.console import Console
        from rich.live import Live
    except ImportError:
        err("status --watch needs rich: pip install 'rocoma-can[live]'")
        return USAGE
    class Watched(Console):
        def on_broken_pipe(self) -> None:
            """Its reader gone (`| head`): rich's own exits 1; every verb's ends 141
            (cli/console.py), and the view's last refresh writes nothing more."""
            self.quiet = True
            raise BrokenPipeError

    if console is None:
        console = Watched()
        if not console.is_terminal:  # piped or logged: no width to fit, do not truncate
            console = Watched(width=160)
    stop = stop or threading.Event()
    end = time.monotonic() + duration if duration is not None else float("inf")
    status: dict[str, Any] | None = None
    answered = 0.0
    try:
        with Live(console=console, refresh_per_second=8, auto_refresh=False) as live:
            while not stop.is_set() and time.monotonic() < end:
                started = time.monotonic()
                problem = ""
                try:
                    status = read()
                    answered = time.time()
                except RocomaError as exc:  # no answer, or an answer spoilt by another
                    problem = str(exc)       # client on the node's one SDO channel: again
                live.update(view(status, problem, answered, label), refresh=True)
                stop.wait(max(0.0, min(interval - (time.monotonic() - started),
                                       end - time.monotonic())))
    except KeyboardInterrupt:  # Ctrl-C is how a watch ends
        pass
    return OK


def view(status: dict[str, Any] | None, problem: str = "", answered: float = 0.0,
         label: str = "the manager") -> RenderableType:
    """One screen of ``status`` (``problem``: why the last question got no answer)."""
    from rich import box
    from rich.console import Group
    from rich.progress_bar import ProgressBar
    from rich.table import Table
    from rich.text import Text

    parts: list[RenderableType] = []
    if problem:
        since = time.strftime("%H:%M:%S", time.localtime(answered)) if answered else "never"
        parts.append(Text(f"STALE: {problem} (last answer {since})", style="bold red"))
    if status is None:
        parts.append(Text(f"waiting for {label} ..."))
        return Group(*parts)

    parts.append(_head(status))

    if status.get("buses"):
        buses = Table(title="buses", title_justify="left", box=box.SIMPLE_HEAD)
        for column in ("bus", "channel", "planned load", "tx errors", "error frames",
                       "fault"):
            buses.add_column(column)
        for b in status["buses"]:
            load = b.get("load")
            buses.add_row(b["name"], b["channel"],
                          "in-process" if load is None else
                          _bar(ProgressBar(total=1.0, completed=min(load, 1.0), width=12),
                               f"{load:.0%}"),
                          str(b["tx_errors"]), str(b["error_frames"]),
                          Text(b.get("fault") or "", style="bold red"))
        parts.append(buses)

    drives = status["drives"]
    table = Table(title="drives", title_justify="left", box=box.SIMPLE_HEAD)
    for column in ("drive", "node", "bring-up", "CiA 402", "NMT", "heartbeat",
                   "position", "velocity", "torque", "fault / homing"):
        numeric = column in ("node", "heartbeat", "position", "velocity", "torque")
        table.add_column(column, no_wrap=column != "fault / homing",
                         justify="right" if numeric else "left")
    for d in drives:
        phase = d["phase"]
        if phase in PHASES[:-1]:
            bring_up: RenderableType = _bar(ProgressBar(
                total=len(PHASES) - 1, completed=PHASES.index(phase), width=10), phase)
        else:
            bring_up = Text(phase, style="bold red" if phase == "FAILED" else "")
        cia = d["cia402_state"] + (" (enabled)" if d["enabled"] and d["cia402_state"]
                                   != "OPERATION_ENABLED" else "")
        age = d.get("heartbeat_age")
        note: RenderableType = Text(d["fault"] or "", style="bold red")
        homing = d.get("homing") or ""
        if homing in ("enabling", "homing"):
            note = _bar(ProgressBar(total=None, pulse=True, width=10), f"homing: {homing}")
        elif homing and not d["fault"]:
            note = Text(f"homing: {homing}")
        table.add_row(d["name"], str(d["node_id"]), bring_up,
                      Text(cia, style=CIA402_STYLES.get(d["cia402_state"], "")),
                      d["nmt_state"], "never" if age is None else f"{age:.2f} s",
                      *(_value(d.get(k)) for k in ("position", "velocity", "torque")), note)
    parts.append(table)
    parts.append(Text(f"{label}, updated "
                      f"{time.strftime('%H:%M:%S', time.localtime(answered))}; Ctrl-C ends "
                      "the view (the manager runs on)", style="dim"))
    return Group(*parts)


def _head(status: dict[str, Any]) -> RenderableType:
    """The manager's lines: state, controller, e-stop, last switch, bring-up, recovery,
    bus fault, cycle."""
    from rich.progress_bar import ProgressBar
    from rich.table import Table
    from rich.text import Text

    head = Table.grid(padding=(0, 2))
    head.add_column(style="bold")
    head.add_column()
    state = status["state"]
    head.add_row("state", Text(f" {state} ", style=STATE_STYLES.get(state, "")))
    head.add_row("controller", status["active"])
    head.add_row("e-stop", ("latched" if status["latched"] else "not latched")
                 + (f"; last cause: {status['estop_cause']}" if status["estop_cause"] else ""))
    head.add_row("last switch", status["last_switch"] + (
        f" (refused: {status['switch_refused']})" if status["switch_refused"] else ""))
    drives = status["drives"]
    ready = sum(d["phase"] == "READY" for d in drives)
    if not status.get("startup_finished"):
        head.add_row("bring-up", _bar(ProgressBar(total=max(1, len(drives)), completed=ready,
                                                  width=30), f"{ready}/{len(drives)} ready"))
    recovery = status.get("recovery") or "none"
    if recovery.startswith("running"):
        head.add_row("recovery", _bar(ProgressBar(total=None, pulse=True, width=30),
                                      recovery))
    elif recovery != "none":
        head.add_row("recovery", recovery)
    if status.get("bus_fault"):
        head.add_row("bus fault", Text(status["bus_fault"], style="bold red"))
    cycle = status.get("cycle")
    if cycle:
        head.add_row("cycle", cycle_text(cycle))
    return head


def _bar(bar: RenderableType, label: str) -> RenderableType:
    from rich.table import Table
    grid = Table.grid(padding=(0, 1))
    grid.add_row(bar, label)
    return grid


def cycle_text(cycle: dict[str, Any]) -> str:
    """The status report's cycle statistics in one line (``status`` prints it too)."""
    def ms(key: str) -> str:
        value = cycle.get(key)
        return "n/a" if value is None else f"{value:.3f} ms"  # (run's last line too)
    waiting = cycle.get("overruns_waiting")  # (None: a manager from before it was counted)
    return (f"{cycle['cycles']} cycles at {cycle['rate']:g} Hz, overruns {cycle['overruns']}"
            + (f" ({waiting} waiting)" if waiting is not None else "") + ", "
            f"period mean {ms('period_mean_ms')} max {ms('period_max_ms')}, jitter p99 "
            f"{ms('jitter_p99_ms')}, work max {ms('work_max_ms')}"
            + (f", spin pauses {cycle['spin_pauses']} (a yield cost a period)"
               if cycle.get("spin_pauses") else ""))


def _value(value: float | None) -> str:
    return "" if value is None else f"{value:+.3f}"
