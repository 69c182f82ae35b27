"""More vendor-file quirks, each as its own small variant of tests/fixtures/eds/minimal.eds
written for the test: a file the project can run runs (check-config, the simulator, the
demo's walk-through with its torque-off), one it cannot is refused in one line naming the
file, the object and why.

    a default PDO mapping naming an object the file does not describe (a vendor object
    left out of the file): the simulator starts that PDO unmapped, the master remaps it
"""
from __future__ import annotations

import logging
from pathlib import Path

import pytest
from fixtures.driver_rig import INCREMENTS_PER_REV, RATED_TORQUE_NM

from rocoma_can.drivers.config import DriveConfig
from rocoma_can.drivers.drive_plan import plan_drive

EDS = Path(__file__).parent / "fixtures" / "eds"


def variant(tmp_path: Path, name: str, *edits: tuple[str, str], add: str = "") -> str:
    """minimal.eds with each (old, new) replaced once (old must be there) and ``add``
    appended."""
    text = (EDS / "minimal.eds").read_text()
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / name
    path.write_text(text + add)
    return str(path)


def drive(path: str, **kw) -> DriveConfig:
    kw.setdefault("modes", ("csp",))
    return DriveConfig("j1", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM, eds=path, **kw)


def walk_through(path: str) -> list[str]:
    from rocoma_can.cli.demo import run_demo
    lines: list[str] = []
    report = run_demo(drives=2, rate=100.0, duration=2.0, out=lines.append, eds=path)
    assert report.ok, "\n".join(lines)
    assert report.steps[-1].name == "loop stop -> torque-off frames"
    return lines


def test_a_default_mapping_naming_an_undescribed_object_runs(tmp_path, sim_segment_factory,
                                                              caplog):
    """TPDO1's default mapping names 0x2001:0, a vendor object the file does not list: the
    simulated drive raised SdoAbortedError from its power-on (a traceback from `demo --eds`
    and `sim --eds`); it starts that PDO unmapped and says so, bring-up remaps it."""
    path = variant(tmp_path, "undescribed_default.eds",
                   ("DefaultValue=0x60610008", "DefaultValue=0x20010008"))
    with caplog.at_level(logging.WARNING, "rocoma_can.drivers.sim.segment"):
        segment = sim_segment_factory([1], eds_path=path)
    assert segment.drives[1].od_value(0x1A00, 0) == 0
    assert "default mapping of 0x1A00 (0x2001:0) names an object it does not describe" \
        in caplog.text
    plan_drive(drive(path))  # check-config: a writable mapping is the master's to set
    walk_through(path)
