"""Shared by every benchmark: summary statistics, the printed table, the JSON result file.

Each benchmark prints one table and writes ``benchmarks/results/<name>.json`` holding the
machine it ran on, its arguments and its rows, so a later run can be compared with this one.
Numbers come from a shared, noisy machine: compare them, never treat them as bounds.
"""
from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: Where the JSON goes; ROCOMA_BENCH_RESULTS redirects it (the smoke test uses a temp dir).
RESULTS = Path(os.environ.get("ROCOMA_BENCH_RESULTS")
               or Path(__file__).resolve().parent / "results")


def stats(samples: Iterable[float]) -> dict[str, float]:
    """median / p99 / max / mean / n of a sample set (empty -> NaNs and n = 0)."""
    a = np.asarray(list(samples) if not isinstance(samples, np.ndarray) else samples,
                   dtype=float)
    if a.size == 0:
        nan = float("nan")
        return {"median": nan, "p99": nan, "max": nan, "mean": nan, "n": 0}
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max()), "mean": float(a.mean()), "n": int(a.size)}


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"nproc": os.cpu_count(), "cpu": cpu, "python": platform.python_version(),
            "platform": platform.platform(), "loadavg": list(os.getloadavg())}


def _cell(value: Any) -> str:
    if isinstance(value, float):
        if value != value:
            return "-"
        return (f"{value:.0f}" if abs(value) >= 1000 else
                f"{value:.1f}" if abs(value) >= 100 else f"{value:.2f}")
    return str(value)


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A plain fixed-width table (also valid Markdown when pasted into the README)."""
    cells = [[_cell(v) for v in row] for row in rows]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]
    def line(vals: Sequence[str]) -> str:  # first column (the label) left, numbers right
        return "| " + " | ".join(v.ljust(w) if i == 0 else v.rjust(w)
                                 for i, (v, w) in enumerate(zip(vals, widths))) + " |"
    sep = "|" + "|".join(("-" * (w + 2)) if i == 0 else ("-" * (w + 1) + ":")
                         for i, w in enumerate(widths)) + "|"
    return "\n".join([line(headers), sep] + [line(r) for r in cells])


def report(name: str, title: str, headers: Sequence[str], rows: Sequence[Sequence[Any]],
           *, args: Any = None, notes: Sequence[str] = (), **extra: Any) -> dict[str, Any]:
    """Print the table and write results/<name>.json; returns what was written."""
    print(f"\n## {title}\n")
    print(table(headers, rows))
    for note in notes:
        print(f"\n{note}")
    sys.stdout.flush()
    result = {"benchmark": name, "title": title, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "machine": machine(), "args": vars(args) if args is not None else {},
              "headers": list(headers), "rows": [list(r) for r in rows],
              "notes": list(notes), **extra}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(result, indent=2, default=_json_default) + "\n")
    print(f"\n(wrote {path})")
    return result


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
