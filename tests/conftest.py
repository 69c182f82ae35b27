"""Suite-wide policy for SocketCAN tests, and the shared fixture plugins.

A test needs real SocketCAN (vcan0/vcan1) when it carries the `vcan` marker, lives in
tests/vcan/, or uses the vcan_bus fixture; the last two are marked automatically. Such tests
run through tools/vcan-run (bash tools/test: `-m vcan` there, `-m "not vcan"` natively).
Where vcan is unavailable they are skipped with the reason, except under CI=true, where that
skip is turned into a failure: CI must never go green by not running them.
"""
from __future__ import annotations

import atexit
import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest

pytest.register_assert_rewrite("fixtures")
from fixtures.bus import in_ci, vcan_problem  # noqa: E402  (after the rewrite hook)

pytest_plugins = ["fixtures.bus", "fixtures.sim", "fixtures.manager_probes",
                  "fixtures.driver_rig", "fixtures.sim_group", "fixtures.running", "fixtures.uml"]

VCAN_DIR = Path(__file__).parent / "vcan"

# Nothing a test runs writes into the home directory: the flight recorder's and the demo's
# default directories are under $XDG_STATE_HOME (processes the tests start inherit it).
_STATE_HOME = tempfile.mkdtemp(prefix="rocoma-test-state-")
os.environ["XDG_STATE_HOME"] = _STATE_HOME
atexit.register(shutil.rmtree, _STATE_HOME, True)


def _needs_vcan(item: pytest.Item) -> bool:
    return item.get_closest_marker("vcan") is not None


@pytest.hookimpl(tryfirst=True)  # before -m deselects: the automatic marks must count
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if VCAN_DIR in item.path.parents or "vcan_bus" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.vcan)
        if _needs_vcan(item) and vcan_problem():
            item.add_marker(pytest.mark.skip(reason=f"vcan unavailable: {vcan_problem()}"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    report = yield
    if report.skipped and in_ci() and _needs_vcan(item) and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.outcome = "failed"
        report.longrepr = f"CI=true: this vcan test must run, but it was skipped: {reason}"
    return report


def vcan_outcomes(stats: dict[str, list]) -> dict[str, str]:
    """Outcome per vcan test id: failed (in any phase) over skipped over passed."""
    outcomes: dict[str, str] = {}
    for outcome, categories in (("failed", ("failed", "error")),
                                ("skipped", ("skipped", "xfailed")),
                                ("passed", ("passed", "xpassed"))):
        for category in categories:
            for report in stats.get(category, ()):
                if "vcan" in getattr(report, "keywords", {}):
                    outcomes.setdefault(report.nodeid, outcome)
    return outcomes


def vcan_durations(stats: dict[str, list]) -> dict[str, float]:
    """Seconds per vcan test id, setup + call + teardown."""
    durations: dict[str, float] = {}
    for reports in stats.values():
        for report in reports:
            if "vcan" in getattr(report, "keywords", {}) and hasattr(report, "duration"):
                durations[report.nodeid] = durations.get(report.nodeid, 0.0) + report.duration
    return durations


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    """Say how many vcan tests really ran; tools/test reads the same numbers, the slowest
    tests and any retried one (a rerun plugin's "rerun" reports: there must be none) from the
    file named by ROCOMA_VCAN_SUMMARY."""
    stats = terminalreporter.stats
    outcomes = list(vcan_outcomes(stats).values())
    runner = os.environ.get("ROCOMA_VCAN_RUNNER", "none")
    counts = {name: outcomes.count(name) for name in ("passed", "failed", "skipped")}
    summary_path = os.environ.get("ROCOMA_VCAN_SUMMARY")
    if summary_path:
        durations = vcan_durations(stats)
        slowest = sorted(durations.items(), key=lambda item: -item[1])[:10]
        retried = sorted({r.nodeid for r in stats.get("rerun", ())})
        Path(summary_path).write_text(json.dumps(dict(counts, runner=runner, slowest=slowest,
                                                      retried=retried)))
    if outcomes or runner != "none":
        terminalreporter.write_sep(
            "-", f"vcan tests: {counts['passed'] + counts['failed']} ran ({counts['passed']} "
                 f"passed, {counts['failed']} failed), {counts['skipped']} skipped; "
                 f"SocketCAN: {runner}")
