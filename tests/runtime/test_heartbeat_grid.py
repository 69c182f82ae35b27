"""drivers/cycle/frames_out.py (the manager's heartbeat): the manager's heartbeat keeps the period
0x1017 declares (issue 33: 500 ms declared, a median of 520 ms measured at 25 Hz, since each beat
was scheduled from the cycle that sent it). The hardware's cycle runs on a simulated clock over
python-can's virtual bus, so the grid is asserted exactly, whatever the load of the machine: each
cycle sends one SYNC, so the frames' order on the bus names the cycle each heartbeat went out in,
and that cycle's time is the beat's timestamp."""
from __future__ import annotations

import math
import random

import pytest
from fixtures.driver_rig import MANAGER_NODE_ID, drive_configs

from rocoma_can import ManagerState
from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.plan.config import Supervision, Timeouts
from rocoma_can.drivers.protocol import cia301

HEARTBEAT = cia301.HEARTBEAT + MANAGER_NODE_ID


def _beats(bus_factory, heartbeat_ms: int, rate: float, cycles: int,
           stall: tuple[int, int] | None = None) -> tuple[list[float], list[float]]:
    """Cycle times and heartbeat times of a run of ``cycles`` cycles, each started up to a
    quarter cycle late (seeded: the same run every time). ``stall``: (cycle, cycles) the
    loop does not run, as when the process is held up."""
    dt = 1.0 / rate
    jitter = random.Random(33)
    # The drive is never there, and its bring-up waits for its boot-up longer than the run
    # lasts: nothing sends a heartbeat out of turn (bring-up does, once a drive's consumer
    # is configured).
    run = (cycles + (stall[1] if stall else 0) + 1) * dt
    hw = CanopenHardware(bus_factory(), drive_configs([1]), MANAGER_NODE_ID, dt,
                         manager_heartbeat_ms=heartbeat_ms,
                         supervision=Supervision(timeouts=Timeouts(boot_wait=2 * run)))
    seen = bus_factory()
    times: list[float] = []
    beats: list[float] = []
    hw.start(now=0.0)
    try:
        k = 0
        for n in range(cycles):
            if stall is not None and n == stall[0]:
                k += stall[1]
            now = k * dt + jitter.uniform(0.0, dt / 4)
            k += 1
            hw.read(now)
            hw.write(ManagerState.FAILPROOF)
            syncs = 0
            while (msg := seen.recv(0.0)) is not None:  # the virtual bus delivers at once
                if msg.arbitration_id == cia301.SYNC:
                    syncs += 1
                elif msg.arbitration_id == HEARTBEAT:
                    assert syncs == 1  # after this cycle's SYNC: it went out in this cycle
                    beats.append(now)
            assert syncs == 1
            times.append(now)
    finally:
        hw.close()
    return times, beats


@pytest.mark.parametrize("heartbeat_ms, rate", [(500, 25.0), (100, 1000 / 30), (250, 200.0)],
                         ids=["issue-33", "period-not-a-multiple", "fast-loop"])
def test_the_heartbeat_keeps_the_declared_grid(bus_factory, heartbeat_ms, rate):
    period = heartbeat_ms / 1000
    times, beats = _beats(bus_factory, heartbeat_ms, rate, cycles=round(90 * period * rate))
    cycle = max(b - a for a, b in zip(times, times[1:]))  # the longest cycle of the run
    # every due time that a cycle reached got its beat, and no other beat went out
    assert len(beats) == math.floor((times[-1] - beats[0]) / period) + 1
    assert len(beats) >= 85
    for i, beat in enumerate(beats[1:], 1):
        due = beats[0] + i * period
        assert due <= beat < due + cycle, (i, beat - due)  # at most one cycle late
        before = max(t for t in times if t < beat)
        assert before < due  # sent in the first cycle at or after its due time
    intervals = [b - a for a, b in zip(beats, beats[1:])]
    mean = sum(intervals) / len(intervals)
    assert abs(mean - period) < cycle / len(intervals)  # no drift: the mean is the period
    assert all(period - cycle < x < period + cycle for x in intervals)


def test_a_stalled_loop_starts_the_grid_again_without_a_burst(bus_factory):
    """A loop held up for several periods sends one beat when it comes back, then beats a
    period apart from there: never the missed beats in a row."""
    heartbeat_ms, rate = 100, 100.0
    period = heartbeat_ms / 1000
    stalled = round(3.5 * period * rate)
    times, beats = _beats(bus_factory, heartbeat_ms, rate, cycles=200,
                          stall=(100, stalled))
    back = times[100]
    cycle = max(b - a for a, b in zip(times[100:], times[101:]))
    after = [b for b in beats if b >= back]
    assert after[0] == back  # the first cycle after the stall beats at once
    assert len(after) == math.floor((times[-1] - back) / period) + 1
    for i, beat in enumerate(after):  # on a grid from there
        assert back + i * period <= beat < back + i * period + cycle, (i, beat - back)
