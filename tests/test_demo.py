"""The embedded demo runs its whole walk-through (shortened) and says so with exit code 0."""
from __future__ import annotations

from rocoma_can.cli import main
from rocoma_can.runtime.demo import run_demo


def test_demo_walk_through_passes():
    lines: list[str] = []
    report = run_demo(drives=3, rate=100.0, duration=3.0, out=lines.append)
    assert report.ok, "\n".join(lines)
    names = [s.name for s in report.steps]
    assert names[0] == "bring-up" and names[-1] == "loop stop -> torque-off frames"
    assert any("failproof" in n for n in names) and any("recovery" in n for n in names)
    assert len(report.latencies) == 3
    assert lines[-1] == "demo passed"


def test_demo_cli_rejects_bad_options(capsys):
    assert main(["demo", "--drives", "0"]) == 2
