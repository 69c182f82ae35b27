"""What ``rocoma-can demo`` says: its steps and report, the drives' notes once each, a
status line a second while it runs, the summary at the end, and where its recording and
plot went. Kept apart from the walk-through (walkthrough.py, steps.py) that produces them."""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from ...node.objects import STATE_NAMES

if TYPE_CHECKING:
    from ...drivers.plan.drive_plan import DrivePlan
    from ...runtime.loop import TimingSummary
    from ...runtime.system import Runtime


@dataclass
class Step:
    name: str
    ok: bool
    detail: str

    def line(self) -> str:
        """As the demo prints it: its verdict (``ok``, ``FAILED``, ``skip``), then what."""
        verdict = "skip" if self.detail.startswith("skipped") else "ok " if self.ok \
            else "FAILED"
        return f"{verdict} {self.name}{': ' + self.detail if self.detail else ''}"


@dataclass
class DemoReport:
    steps: list[Step] = field(default_factory=list)
    latencies: list[tuple[str, float, int]] = field(default_factory=list)  # what, s, cycles
    recording: Path | None = None      # the run's trace.mcap (with a candump .log per bus)
    plot: Path | None = None           # its PNG
    flight_records: list[Path] = field(default_factory=list)  # one per e-stop (grouped)
    walk_time: float = 0.0             # s from the walk-through's start to the loop's stop
    interrupted: str = ""              # the signal that stopped the loop mid-walk-through

    @property
    def ok(self) -> bool:
        return bool(self.steps) and all(s.ok for s in self.steps) and not self.interrupted


def note_lines(plans: Mapping[str, DrivePlan]) -> dict[str, str]:
    """Each drive-plan note once, naming its drives: the demo's drives share one file, so
    a note per drive would say the same thing as many times as there are drives."""
    drives: dict[str, list[str]] = {}
    for name, plan in plans.items():
        for note in plan.notes:
            drives.setdefault(note, []).append(name)
    everyone = list(plans)
    lines = {}
    for note, names in drives.items():
        start = everyone.index(names[0])
        run = len(names) > 3 and everyone[start:start + len(names)] == names
        who = f"{names[0]}..{names[-1]}" if run else ", ".join(names)
        lines[note] = f"  note: {who}: {note}"
    return lines


class Said(logging.Filter):
    """Drops a log record that repeats one of these notes (the hardware's line per drive)."""

    def __init__(self, notes: set[str]) -> None:
        super().__init__()
        self.notes = notes

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(message.endswith(": " + note) for note in self.notes)


def plot_run(directory: Path, report: DemoReport, out: Callable[[str], None],
             errors: Sequence[str] = ()) -> None:
    """After the run (the recording closed): draw it, say where both are. ``errors``: why
    the recording stopped (the first first: a full disk, the writer process gone): said
    instead of "every cycle and frame", and a failed step, as ``run`` exits 1 for it."""
    from ...record.plot import PlotError, plot
    report.recording = directory / "trace.mcap"
    if errors:
        recording_stopped(report, errors)
        out(f"recording: {report.recording} stopped early, what was written stays: "
            f"{errors[0]}")
    else:
        logs = ", ".join(str(p) for p in sorted(directory.glob("*.log")))
        out(f"recording: {report.recording} (every cycle and frame; candump logs: {logs})")
    try:
        report.plot = plot(report.recording, directory / "demo.png",
                           title=f"rocoma-can demo: {len(report.steps)} steps, "
                                 f"{'passed' if report.ok else 'FAILED'}")
    except PlotError as exc:
        out(f"plot: none ({exc})")
        return
    out(f"plot: {report.plot}")


def recording_stopped(report: DemoReport, errors: Sequence[str]) -> None:
    """The recording's failure as a failed step, once (seen before the summary, or at the
    close)."""
    if errors and not any(step.name == "recording" for step in report.steps):
        report.steps.append(Step("recording", False, errors[0]))


def status_ticker(rt: Runtime, stop: threading.Event, out: Callable[[str], None]) -> None:
    """A status line a second until ``stop`` (the demo's thread while the loop runs)."""
    while not stop.wait(1.0):
        hw, mgr, s = rt.hardware, rt.manager, rt.loop.stats
        out(f"  [{s.cycles:6d} cycles] {STATE_NAMES[int(mgr.state)]:9s} "
            f"{mgr.active_controller_name:12s} enabled {int(hw.enabled.sum())}/"
            f"{len(hw.drives_config)} q0 {hw.state.position[0]:+.3f} rad "
            f"overruns {s.overruns} tx errors {hw.tx_errors}")


#: overruns above this share of the cycles point at ``doctor --timing`` (issue 36's target)
HOST_HINT_SHARE = 0.001


def host_hint(timing: TimingSummary) -> str | None:
    """For a run with more overruns than HOST_HINT_SHARE: how to tell the host's share of
    them (a shared virtual machine's speed alone can cost a loop that much), else None."""
    if timing.overruns <= HOST_HINT_SHARE * timing.cycles:
        return None
    return (f"over {100 * HOST_HINT_SHARE:g} % of the cycles: `rocoma-can doctor --timing` "
            "measures what this host allows a loop")


def summary(out: Callable[[str], None], report: DemoReport, timing: TimingSummary,
             rt: Runtime) -> None:
    out("")
    out("summary")
    out(f"  {'steps':28s} {sum(s.ok for s in report.steps)}/{len(report.steps)} ok")
    out(f"  {'walk-through':28s} {report.walk_time:.1f} s")
    out(f"  {'cycles':28s} {timing.cycles}")
    if rt.loop.priority:
        refused = rt.loop.realtime_refused
        out(f"  {'loop priority':28s} " + (f"SCHED_FIFO {rt.loop.priority}"
                                          if rt.loop.ran_realtime else
                                          "normal: " + "; ".join(refused)))
    waiting = timing.overruns_waiting
    out(f"  {'overruns (past their period)':28s} {timing.overruns}"
        + (f" ({timing.overruns - waiting} on the CPU, {waiting} waiting off it)"
           if timing.overruns else ""))
    hint = host_hint(timing)
    if hint is not None:
        out(f"  {'':28s} {hint}")
    if rt.loop.yield_pauses:
        out(f"  {'spin pauses':28s} {rt.loop.yield_pauses} (a yield cost the loop a period; "
            "it spun on the CPU for 5 s after each)")
    out(f"  {'period mean / max':28s} {timing.period_mean * 1e3:.2f} / "
        f"{timing.period_max * 1e3:.2f} ms")
    out(f"  {'jitter p99 / max':28s} {timing.jitter_p99 * 1e3:.2f} / "
        f"{timing.jitter_max * 1e3:.2f} ms")
    out(f"  {'frames per cycle':28s} {rt.hardware.frames_per_cycle} "
        f"(PDOs of {len(rt.hardware.drives_config)} drives + SYNC)")
    out(f"  {'tx errors':28s} {rt.hardware.tx_errors}")
    for what, took, cycles in report.latencies:
        out(f"  {'latency ' + what:28s} {took * 1e3:.1f} ms (~{cycles} cycles)")
    failed = [s.name for s in report.steps if not s.ok]
    if report.interrupted:
        walked = next((k for k, s in enumerate(report.steps) if s.name == "walk-through"),
                      len(report.steps))
        out(f"demo interrupted ({report.interrupted}) after {walked} steps of the "
            "walk-through" + (f"; FAILED: {', '.join(failed)}" if failed else ""))
    else:
        out("demo " + ("passed" if report.ok else "FAILED: " + ", ".join(failed)))
