"""The live view's channels in recordings (record/live_channels.py) as a reader finds them
after the fact: the samples of /rocoma/manager and /tf come at the documented rate on a
loop's jittery rows."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rocoma_can.cli.demo_config import demo_urdf
from rocoma_can.live.urdf import Robot, parse_urdf
from rocoma_can.record.live_channels import SAMPLE_RATE, Facts, LiveChannels
from rocoma_can.record.trace import McapWriter, RowLayout, read_messages

JOINTS = ["joint1", "joint2"]


@pytest.mark.parametrize("rate", [100.0, 1000.0, 20.0])
def test_samples_come_at_the_documented_rate_on_a_jittery_loop(rate, tmp_path):
    """10 s of a loop's rows, each up to 40 % of a period late (a loaded bench), handed over
    in the writer's 50 ms batches: /rocoma/manager and /tf come 50 times a second on
    average (each at the first row at or after its time), every cycle of a loop slower
    than that."""
    period, seconds = 1.0 / rate, 10.0
    count = int(seconds * rate)
    rows = np.zeros((count, RowLayout(JOINTS).width))
    rows[:, 0] = 100.0 + np.arange(count) * period + np.random.default_rng(1).uniform(
        0.0, 0.4 * period, count)
    robot = parse_urdf(demo_urdf(JOINTS).encode(), "demo")
    batch = max(1, int(0.05 * rate))
    messages = _live_file(tmp_path, [rows[first:first + batch]
                                     for first in range(0, count, batch)], period, robot,
                          Facts())
    times = {topic: np.array([t for other, t, _ in messages if other == topic])
             for topic in ("/rocoma/manager", "/tf")}
    assert list(times["/tf"]) == list(times["/rocoma/manager"])
    if rate <= SAMPLE_RATE:
        assert len(times["/tf"]) == count
        return
    assert abs(len(times["/tf"]) - seconds * SAMPLE_RATE) <= 1
    # sample n in [first + n / SAMPLE_RATE, first + (n + 1) / SAMPLE_RATE): none skipped
    since = (times["/tf"] - times["/tf"][0]) / 1e9 + 1e-7
    assert list(np.floor(since * SAMPLE_RATE)) == list(range(len(since)))


def _live_file(tmp_path: Path, batches: list[np.ndarray], period: float,
               robot: Robot | None, facts: Facts) -> list[tuple[str, int, dict[str, Any]]]:
    """The messages LiveChannels makes of rows handed over in ``batches`` (the first
    numbered 0), as a reader finds them in the file."""
    path = tmp_path / "live.mcap"
    with open(path, "wb") as stream:
        writer = McapWriter(stream, JOINTS)
        live = LiveChannels(writer, RowLayout(JOINTS), period, robot, facts)
        first = 0
        for rows in batches:
            live.cycles(rows, first, {0: "pd"}, 0.0)
            first += len(rows)
        writer.finish()
    return list(read_messages(str(path)))
