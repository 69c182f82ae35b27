"""``rocoma-can plot``: one PNG of a trace (``run --record``'s trace.mcap, a flight record,
the demo's recording) that a person reads without the code.

Panels, top to bottom, on one time axis (seconds from the first cycle): the manager's state
as a coloured band (OK green, EMERGENCY orange, FAILPROOF red) with the active controller
written in it; joint positions (solid) with their position targets (dashed, only while the
joint is commanded in position); measured (solid) and commanded (dashed) torques; the cycle
period. Every e-stop is a red line through them all, numbered, its cause listed under the
figure (the loop's own stop, which ends in torque-off too, is a grey dotted one).
Beside the period, a histogram of its deviation from the nominal period (the jitter).

Drawing needs matplotlib (the optional extra ``rocoma-can[plot]``); reading needs mcap
(``rocoma-can[record]``). Nothing here runs in the loop.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import RocomaError
from ..events import STOP_CAUSE

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: colours of the manager states on the band (and in the README's legend)
STATE_COLOURS = {"OK": "#4caf50", "EMERGENCY": "#ff9800", "FAILPROOF": "#e53935"}
#: command modes whose position target the drive follows (joints.JointMode CSP; PP/IP carry
#: the same target)
POSITION_MODES = (8,)
#: the axes' titles, in order: what a reader (and the tests) find the panels by
PANELS = ("Manager state and active controller", "Joint position [rad]", "Torque [Nm]",
          "Cycle period [ms]", "Jitter")


#: e-stops listed under the figure at most
MAX_LISTED = 8


class PlotError(RocomaError):
    """A file that cannot be plotted: not MCAP, no cycles, or a missing optional package."""


@dataclass
class Trace:
    """A trace's cycles as arrays (rows: cycles; joint columns) and its events."""
    time: np.ndarray                  # s since the first cycle (its log time)
    period: np.ndarray                # s; NaN for the first cycle
    state: list[str]
    controller: list[str]
    position: np.ndarray
    command_position: np.ndarray      # NaN where the joint was not commanded in position
    torque: np.ndarray
    command_torque: np.ndarray
    joints: int
    names: list[str] = field(default_factory=list)   # the joints' names, in column order
    events: list[tuple[float, str, str, str]] = field(default_factory=list)
    """(s since the first cycle, kind, state, cause)"""

    @property
    def estops(self) -> list[tuple[float, str]]:
        """(time, cause) of each e-stop: from the event channel; for traces without one,
        where the state fell to EMERGENCY or FAILPROOF."""
        stops = [(t, cause) for t, kind, _, cause in self.events if kind == "emergency_stop"]
        if stops or self.events:
            return stops
        rank = {"FAILPROOF": 0, "EMERGENCY": 1, "OK": 2}
        return [(float(self.time[k]), f"state {b}")
                for k, (a, b) in enumerate(zip(self.state, self.state[1:]), 1)
                if rank.get(b, 2) < rank.get(a, 2)]


def load_trace(path: str | Path, notes: list[str] | None = None) -> Trace:
    """The trace in ``path``; PlotError says why a file cannot be read, in one line; a file
    cut short is read up to the cut, said in ``notes`` (trace.read_messages)."""
    from .trace import CYCLE_TOPIC, EVENT_TOPIC, TraceError, read_trace, recorded_joint_names
    rows: list[tuple[int, dict[str, Any]]] = []
    raw_events: list[tuple[int, dict[str, Any]]] = []
    try:
        for topic, log_time, msg in read_trace(str(path), notes):
            if topic == CYCLE_TOPIC:
                rows.append((log_time, msg))
            elif topic == EVENT_TOPIC:
                raw_events.append((log_time, msg))
    except ImportError:
        raise PlotError("reading MCAP needs the mcap package: "
                        "pip install 'rocoma-can[record]'") from None
    except TraceError as exc:
        raise PlotError(f"{path}: not a rocoma-can trace: {exc}") from None
    if not rows:
        raise PlotError(f"{path}: no cycles ({CYCLE_TOPIC}) to plot")
    joints = len(rows[0][1]["position"])  # every row alike: read_trace checked them
    t0 = rows[0][0]
    names = recorded_joint_names(str(path), joints) or [f"joint {j}" for j in range(joints)]

    def matrix(key: str) -> np.ndarray:
        return np.array([m[key] for _, m in rows], dtype=float).reshape(len(rows), joints)

    mode = matrix("command_mode")
    target = matrix("command_position")
    target[~np.isin(mode, POSITION_MODES)] = np.nan
    return Trace(
        time=np.array([(t - t0) / 1e9 for t, _ in rows]),
        period=np.array([m["period"] for _, m in rows], dtype=float),
        state=[m["state"] for _, m in rows], controller=[m["controller"] for _, m in rows],
        position=matrix("position"), command_position=target,
        torque=matrix("torque"), command_torque=matrix("command_torque"), joints=joints,
        names=names,
        events=[((t - t0) / 1e9, m.get("kind", ""), m.get("state", ""), m.get("cause", ""))
                for t, m in raw_events])


def _runs(values: list[str]) -> list[tuple[int, int, str]]:
    """(first, end, value) of each run of equal values."""
    out, start = [], 0
    for k in range(1, len(values) + 1):
        if k == len(values) or values[k] != values[start]:
            out.append((start, k, values[start]))
            start = k
    return out


def figure(trace: Trace, title: str = "") -> Figure:
    """The figure (matplotlib's object-oriented API: no pyplot state, safe in any thread)."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.patches import Patch
    except ImportError:
        raise PlotError("plotting needs matplotlib: pip install 'rocoma-can[plot]'") from None
    t = trace.time
    fig = Figure(figsize=(11, 9), dpi=80, layout="constrained")
    grid = fig.add_gridspec(4, 2, width_ratios=(4, 1), height_ratios=(0.5, 2, 2, 1.2))
    band = fig.add_subplot(grid[0, 0])
    pos = fig.add_subplot(grid[1, 0], sharex=band)
    tq = fig.add_subplot(grid[2, 0], sharex=band)
    per = fig.add_subplot(grid[3, 0], sharex=band)
    hist = fig.add_subplot(grid[3, 1])
    end = float(t[-1]) + (float(np.nanmedian(trace.period)) if len(t) > 1 else 0.0)
    edges = np.append(t, end)

    for first, stop, state in _runs(trace.state):
        band.axvspan(edges[first], edges[stop], color=STATE_COLOURS.get(state, "#9e9e9e"),
                     alpha=0.8, linewidth=0)
    for first, stop, name in _runs(trace.controller):
        if (edges[stop] - edges[first]) / max(end, 1e-9) < 0.012 * len(name):
            continue  # too short a run to write in
        band.text((edges[first] + edges[stop]) / 2, 0.5, name, ha="center", va="center",
                  fontsize=8, clip_on=True, transform=band.get_xaxis_transform())
    band.set_yticks([])
    band.set_title(PANELS[0], fontsize=10, loc="left")
    band.legend(handles=[Patch(color=c, label=s) for s, c in STATE_COLOURS.items()],
                loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)

    colours = [f"C{j % 10}" for j in range(trace.joints)]
    for j, colour in enumerate(colours):
        pos.plot(t, trace.position[:, j], color=colour, linewidth=1.2, label=trace.names[j])
        pos.plot(t, trace.command_position[:, j], color=colour, linewidth=0.9, linestyle="--")
        tq.plot(t, trace.torque[:, j], color=colour, linewidth=1.0)
        tq.plot(t, trace.command_torque[:, j], color=colour, linewidth=0.8, linestyle="--")
    pos.set_title(PANELS[1] + "  (solid: measured, dashed: target)", fontsize=10, loc="left")
    pos.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    tq.set_title(PANELS[2] + "  (solid: measured, dashed: commanded)", fontsize=10, loc="left")

    ms = trace.period * 1e3
    nominal = float(np.nanmedian(ms)) if np.isfinite(ms).any() else float("nan")
    per.plot(t, ms, color="#37474f", linewidth=0.8)
    per.axhline(nominal, color="#90a4ae", linestyle=":", linewidth=1)
    per.set_title(PANELS[3], fontsize=10, loc="left")
    per.set_xlabel("time [s] since the first cycle")
    jitter = (ms - nominal)[np.isfinite(ms)]
    if len(jitter):
        hist.hist(jitter, bins=40, color="#607d8b")
        hist.set_yscale("log")
    hist.set_title(PANELS[4], fontsize=10, loc="left")
    hist.set_xlabel(f"period - {nominal:.2f} ms [ms]")

    lines = []
    for number, (when, cause) in enumerate(trace.estops, 1):
        own = cause.startswith(STOP_CAUSE)  # the loop's own stop ends in torque-off too
        colour = "#616161" if own else "#b71c1c"
        for ax in (band, pos, tq, per):
            ax.axvline(when, color=colour, linewidth=1.2, linestyle=":" if own else "-")
        band.annotate(str(number), (when, 1.0), xycoords=("data", "axes fraction"),
                      xytext=(0, 2), textcoords="offset points", fontsize=8, color=colour,
                      ha="center", va="bottom", fontweight="bold", annotation_clip=False)
        lines.append(f"{number}  {when:.3f} s  {'' if own else 'e-stop: '}"
                     f"{cause or 'no cause given'}")
    if lines:
        fig.supxlabel("\n".join(lines[:MAX_LISTED] + (
            [f"... and {len(lines) - MAX_LISTED} more"] if len(lines) > MAX_LISTED else [])),
            x=0.01, ha="left", fontsize=8, color="#b71c1c")
    band.set_xlim(0.0, end)
    for ax in (pos, tq, per):
        ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def plot(source: str | Path, out: str | Path | None = None, title: str = "",
         notes: list[str] | None = None) -> Path:
    """Draw ``source`` to ``out`` (default: beside it, ``.png``) and return the PNG's path;
    the title defaults to the file's name (marked when the file was cut short: ``notes``
    says how)."""
    said: list[str] = []
    trace = load_trace(source, said)
    if notes is not None:
        notes += said
    if said and not title:  # (the note's last words: "read up to the cut" / "the damage")
        title = f"{source} ({said[0].split(' (', 1)[0]}: {said[0].rsplit(': ', 1)[-1]})"
    target = Path(out) if out else Path(source).with_suffix(".png")
    try:
        fig = figure(trace, title=title or str(source))
    except ValueError as exc:  # values no trace of ours holds (limits of NaN or inf)
        raise PlotError(f"{source}: not a rocoma-can trace: cannot draw it: {exc}") from None
    try:
        fig.savefig(target)
    except (OSError, ValueError) as exc:  # no such directory; a format matplotlib lacks
        raise PlotError(f"{target}: cannot write the plot: {exc}") from None
    return target
