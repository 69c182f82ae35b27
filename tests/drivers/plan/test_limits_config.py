"""``limits:`` in a drive's config (drivers/plan/config.py), its drive units
(drivers/plan/limits.py) and what check-config says of it: which limits the drive enforces,
which the manager only."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from rocoma_can import eds
from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_plan import plan_drive
from rocoma_can.drivers.plan.limits import drive_writes
from rocoma_can.drivers.plan.scaling import Scaling
from rocoma_can.runtime.config import ConfigError, load, validate

BASE = {"name": "knee", "node_id": 1, "increments_per_rev": 4096, "rated_torque_nm": 2.0}


def drive(**kw) -> DriveConfig:
    return DriveConfig.from_dict({**BASE, **kw})


@pytest.mark.parametrize("limits, message", [
    ({"position": [1.0, -1.0]}, "limits.position min (1.0) must be below max (-1.0)"),
    ({"position": [0.0, math.inf]}, "limits.position must be [min, max] in rad"),
    ({"position": 1.0}, "limits.position must be [min, max] in rad"),
    ({"velocity": -1.0}, "limits.velocity must be a positive number, got -1.0"),
    ({"torque": math.nan}, "limits.torque must be a positive number"),
    ({"following_error": 0}, "limits.following_error must be a positive number, got 0"),
    ({"following_error_cycles": 0}, "limits.following_error_cycles must be a whole number"),
    ({"torgue": 1.0}, "limits.torgue unknown, did you mean 'torque'?"),
    ([1, 2], "limits must be a mapping of position, velocity"),
])
def test_bad_limits_are_one_line_naming_the_drive(limits, message):
    with pytest.raises(ValueError) as info:
        drive(limits=limits)
    assert str(info.value).startswith("drive 'knee': ") and message in str(info.value)
    assert "\n" not in str(info.value)


def test_limits_set_the_managers_limits_too():
    d = drive(limits={"position": [-1.0, 2.0], "velocity": 3.0, "torque": 4.0})
    assert (d.position_min, d.position_max, d.max_velocity, d.max_torque_nm) == \
        (-1.0, 2.0, 3.0, 4.0)
    scaling = Scaling([d])  # the manager's clip: the same numbers
    position, velocity, torque = np.array([5.0]), np.array([-9.0]), np.array([9.0])
    scaling.clip_command(position, velocity, torque)
    assert (position[0], velocity[0], torque[0]) == (2.0, -3.0, 4.0)


def test_an_old_key_that_disagrees_with_limits_is_an_error_and_one_that_agrees_is_not():
    with pytest.raises(ValueError, match="position_max = 1.0 and limits.position = "
                                         r"\(-1.0, 2.0\) disagree; keep limits.position"):
        drive(position_max=1.0, limits={"position": [-1.0, 2.0]})
    assert drive(max_velocity=3.0, limits={"velocity": 3.0}).max_velocity == 3.0


def test_old_keys_stay_the_managers_only_and_are_never_written():
    d = drive(position_min=-1.0, position_max=1.0, max_torque_nm=3.0)
    assert d.manager_only_limits() == ["position_min", "position_max", "max_torque_nm"]
    assert drive_writes(d, plan_drive(d).caps, 0.002) == []


def test_drive_units_are_rounded_outward_and_a_negative_gear_swaps_min_and_max():
    d = drive(gear_ratio=-10.0, limits={"position": [-1.0, 0.5], "velocity": 2.0,
                                        "torque": 10.0, "following_error": 0.01,
                                        "following_error_cycles": 4})
    writes = {(w.index, w.subindex): w.value for w in drive_writes(d, plan_drive(d).caps, 0.002)}
    per_rad = 4096 * 10 / (2 * math.pi)
    assert writes == {
        (0x607D, 1): math.floor(-0.5 * per_rad), (0x607D, 2): math.ceil(1.0 * per_rad),
        (0x607F, 0): math.ceil(2.0 * per_rad),
        (0x6080, 0): math.ceil(2.0 * 10 * 60 / (2 * math.pi)),
        (0x6072, 0): 500,  # 10 Nm at the joint = 1 Nm at the motor = half its rated 2 Nm
        (0x6065, 0): math.ceil(0.01 * per_rad), (0x6066, 0): 16}  # 2 x 4 cycles x 2 ms


def test_a_position_beyond_the_drives_integer32_is_a_config_problem():
    with pytest.raises(ValueError, match=r"limits.position max 10000 rad is beyond what the "
                                         r"drive's position \(INT32 increments"):
        plan_drive(drive(gear_ratio=1000.0, limits={"position": [0.0, 1e4]}))


def _without(tmp_path: Path, *indices: int) -> str:
    """The shipped EDS without the given objects."""
    lines, skip = [], False
    for line in Path(eds.path(eds.CIA402_DRIVE)).read_text().splitlines():
        if line.startswith("["):
            skip = any(line.upper().startswith(f"[{i:04X}") for i in indices)
        if not skip and not any(line.upper().endswith(f"=0X{i:04X}") for i in indices):
            lines.append(line)
    path = tmp_path / "drive.eds"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def test_check_config_says_which_limits_the_drive_enforces_and_which_only_the_manager(
        tmp_path):
    path = _without(tmp_path, 0x607F, 0x6080, 0x6066)
    d = drive(eds=path, modes=["csp"], max_torque_nm=3.0,
              limits={"position": [-1.0, 1.0], "velocity": 2.0, "following_error": 0.05})
    report = plan_drive(d).report()
    enforced = [line for line in report if "limits the drive enforces" in line]
    assert enforced == ["  limits the drive enforces (written at bring-up): position (0x607D:1 = "
                        "-652 increments, 0x607D:2 = 652 increments); following_error (0x6065 "
                        "= 33 increments)"]
    only = [line for line in report if "limits only the manager enforces" in line]
    assert only == ["  limits only the manager enforces: velocity (its file has no writable "
                    "0x607F or 0x6080); max_torque_nm (old key: under limits: the drive "
                    "enforces it too)"]
    assert "  following error: e-stop after 3 cycles beyond 0.05 rad in CSP" in report


def test_check_config_without_limits_says_the_drive_keeps_its_own():
    assert "  limits: none configured (the drive keeps its own, as commissioned)" in \
        plan_drive(drive()).report()


def test_the_following_error_watch_keeps_nothing_allocated_and_faults_after_n_cycles():
    import tracemalloc

    from rocoma_can.drivers.cycle.supervision import FollowingErrorWatch, Supervisor
    drives = [DriveConfig.from_dict({**BASE, "name": f"j{i}", "node_id": i,
                                     "limits": {"following_error": 0.1}}) for i in range(1, 25)]
    watch = FollowingErrorWatch(drives, np.ones(24, dtype=bool))
    sup = Supervisor(drives, 5, 2.5)
    actual, targets = np.zeros(24), np.full(24, 0.05)  # within the window
    for _ in range(10):  # warm up
        watch.tracking.fill(True)
        watch.check(actual, sup, 0.0)
        watch.sent(targets)
    tracemalloc.start()
    try:
        before = tracemalloc.take_snapshot()
        for _ in range(1000):
            watch.tracking.fill(True)
            watch.check(actual, sup, 0.0)
            watch.sent(targets)
        grown = sum(s.size_diff for s in tracemalloc.take_snapshot().compare_to(before, "lineno")
                    if "supervision.py" in str(s.traceback))
    finally:
        tracemalloc.stop()
    assert grown <= 0 and not sup.pending
    watch.tracking.fill(True)
    for _ in range(3):  # beyond for the configured 3 cycles: one fault
        watch.check(np.full(24, 0.2), sup, 1.0)
        watch.tracking.fill(True)
    assert len(sup.pending) == 24 and "beyond the window 0.1 rad for 3 cycles" in \
        sup.pending[0].cause


@pytest.mark.parametrize("limits, name", [({"position": [-1.0, 4.0]}, "limits.position max"),
                                          ({"position": [-4.0, 1.0]}, "limits.position min"),
                                          ({"position_max": 4.0}, "position_max")])
def test_a_position_limit_the_drives_int32_position_cannot_hold_is_refused(limits, name):
    """At 2**32 increments a turn (a 32-bit encoder's 0x608F) the drive's INT32 position
    covers half a turn each way: a joint past it reads as the other end of the range, so a
    limit beyond it guards nothing."""
    given = {"limits": limits} if "position" in limits else limits  # or the old keys
    with pytest.raises(ValueError) as info:
        drive(increments_per_rev=1 << 32, **given)
    value = limits["position"][1 if name.endswith("max") else 0] if "position" in limits \
        else limits["position_max"]
    assert str(info.value) == (
        f"drive 'knee': {name} {value:g} rad is beyond what the drive's position (INT32 "
        f"increments, 0x6064/0x607A) holds at {1 << 32} increments a turn and gear ratio "
        f"1: +-3.142 rad")
    drive(increments_per_rev=1 << 32, limits={"position": [-3.0, 3.0]})  # inside: taken
    drive(increments_per_rev=1 << 32)  # none given: nothing to refuse


# -- 0x6066 is computed once, at the loop's rate, for check-config and bring-up alike --------

def _config(rate: float, cycles: int) -> dict:
    return {"bus": {"interface": "virtual", "channel": "limits-rate"}, "rate": rate,
            "drives": [{**BASE, "name": "j1", "limits": {"following_error": 0.05,
                                                         "following_error_cycles": cycles}}],
            "controllers": [{"name": "pd", "plugin": "pd", "emergency": "damp"}],
            "emergency_controllers": [{"name": "damp", "plugin": "damp"}]}


def _timeout(plan) -> int:
    (value,) = [w.value for w in plan.limit_writes if w.index == 0x6066]
    return value


def test_check_config_refuses_a_following_error_time_out_the_drive_cannot_hold_at_its_rate():
    """4000 cycles at 100 Hz is 80 s: 0x6066 (UNSIGNED16, ms) cannot hold it. check-config
    took a 1 ms period (8000 ms: accepted) and bring-up the loop's, which refused it."""
    with pytest.raises(ConfigError) as refused:
        validate(_config(100, 4000))
    (problem,) = refused.value.problems
    assert "drives[0]: drive 'j1': limits.following_error is 80000 ms in 0x6066:0 " \
           "(following error time out), which its data type cannot hold" in problem
    assert "2 x following_error_cycles 4000 x 10 ms at 100 Hz" in problem
    assert _timeout(validate(_config(1000, 4000)).plans["j1"]) == 8000  # 1 kHz: it fits


def test_run_rate_is_the_rate_0x6066_is_checked_at(tmp_path):
    """``run --rate 100`` over a 1 kHz file: checked at the rate the loop will run."""
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(_config(1000, 4000)))
    assert _timeout(load(path).plans["j1"]) == 8000
    with pytest.raises(ConfigError, match="80000 ms in 0x6066:0"):
        load(path, rate=100)


@pytest.mark.parametrize("rate", [100, 250, 1000])
def test_check_config_and_bring_up_write_one_0x6066(rate):
    """What check-config plans is what the hardware (bring-up) plans, at the config's
    rate: twice the manager's cycles, in ms."""
    config = validate(_config(rate, 3))
    hw = CanopenHardware(config.bus, config.drives, 100, config.dt)
    try:
        assert _timeout(config.plans["j1"]) == _timeout(hw.plans[0]) \
            == math.ceil(2 * 3 * 1000 / rate)
    finally:
        hw.close()


def test_check_config_says_0x6066_in_ms_at_the_rate():
    report = validate(_config(100, 3)).plans["j1"].report()
    (line,) = [line for line in report if "limits the drive enforces" in line]
    assert "0x6066 = 60 ms (2 x 3 cycles of 10 ms)" in line, line
