"""drivers/bringup/drive_bringup.py (0x1016, 0x6007), drivers/sim/nmt.py: the manager process is
killed (SIGKILL): every drive switches itself off.

Nothing of the manager survives a SIGKILL (its heartbeat comes from the control loop, not a
kernel BCM task), so each drive's heartbeat consumer (0x1016; consumer time = the setup's
consumer_factor x the manager's heartbeat period) expires and its abort connection option
(0x6007 = disable voltage) takes the power stage off: within the consumer time plus one
period of the kill.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fixtures import driver_rig  # tests/ is on sys.path (conftest.py); the subprocess too

from rocoma_can.drivers.protocol.cia402 import State402

NODES = driver_rig.VCAN.nodes
HEARTBEAT_MS = 200
TESTS = Path(__file__).resolve().parents[1]


@pytest.mark.vcan
def test_killed_manager_process_drives_switch_off_within_the_consumer_time(sim_segment_factory):
    segment = sim_segment_factory(NODES, channel="vcan0", interface="socketcan")
    code = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); "
            "from fixtures import driver_rig; "
            f"driver_rig.serve('vcan0', 'socketcan', {NODES!r}, {HEARTBEAT_MS}, 120.0)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # bounded: serve() exits by its budgets without ENABLED
        assert line.strip() == "ENABLED", (line, proc.stderr.read() if proc.poll() else "")
        assert all(d.state402 == State402.OPERATION_ENABLED for d in segment.drives.values())
        time.sleep(0.3)  # a few heartbeats while enabled
        os.kill(proc.pid, signal.SIGKILL)
        killed = time.monotonic()
        # each consumer times out at most one period after the last heartbeat before the kill
        bound = driver_rig.VCAN.consumer_factor * HEARTBEAT_MS / 1000 + HEARTBEAT_MS / 1000
        elapsed = driver_rig.seconds_until_all_off(segment, killed, bound + 2.0)
        assert elapsed < bound, elapsed
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        proc.stdout.close()
        proc.stderr.close()
