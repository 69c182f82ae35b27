"""controllers/tracking_monitor.py: the worker example: a 30 Hz worker started in initialize,
cancelled in pre_stop."""
from __future__ import annotations

import threading
import time

from fixtures.joint_plant import JointPlant, attach

from rocoma_can.controllers.tracking_monitor import WORKER_NAME, TrackingMonitor

DT = 0.001
WAIT = 5.0


def worker_threads(name: str) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == f"{name}/{WORKER_NAME}"]


def wait_for(predicate, timeout: float = WAIT) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_worker_runs_from_initialize_until_pre_stop_and_reports_tracking_error():
    plant = JointPlant(2)
    ctrl = attach(TrackingMonitor("monitor", target=[0.2, -0.1], mode="CSP",
                                  velocity_limit=1.0), plant)
    assert ctrl.create(DT)
    assert ctrl.snapshot() is None and not worker_threads("monitor")
    assert ctrl.initialize(DT)
    assert len(worker_threads("monitor")) == 1
    assert ctrl.worker.is_running
    plant.run(ctrl.advance, 300)  # CSP on the ideal plant: at the target after 200 cycles
    assert wait_for(lambda: ctrl.snapshot() is not None)
    seen = ctrl.snapshot().samples
    assert wait_for(lambda: ctrl.snapshot().samples >= seen + 2)  # sampled at rest
    stats = ctrl.snapshot()
    assert stats.names == ("joint0", "joint1")
    assert stats.last == (0.0, 0.0)
    assert all(0.0 <= r <= m <= 0.2 for r, m in zip(stats.rms, stats.max_abs))
    assert ctrl.pre_stop()
    assert not worker_threads("monitor")
    assert not ctrl.worker.is_running
    samples = ctrl.snapshot().samples
    time.sleep(0.1)  # three periods: a live worker would have sampled again
    assert ctrl.snapshot().samples == samples


def test_worker_sees_a_lagging_joint():
    plant = JointPlant(1)
    ctrl = attach(TrackingMonitor("monitor", target=0.5, kp=20.0, kd=1.0,
                                  monitor_frequency=100.0), plant)
    assert ctrl.create(DT)
    assert ctrl.initialize(DT)
    try:
        ctrl.advance(DT)
        # The reference stepped to 0.5 while the joint is still at 0.
        assert wait_for(lambda: ctrl.snapshot() is not None and ctrl.snapshot().last[0] > 0.45)
        assert ctrl.snapshot().max_abs[0] == ctrl.snapshot().last[0]
    finally:
        assert ctrl.pre_stop()


def test_reset_restarts_the_worker_without_leaking_a_thread():
    plant = JointPlant(1)
    ctrl = attach(TrackingMonitor("monitor"), plant)
    assert ctrl.create(DT)
    for _ in range(3):
        assert ctrl.initialize(DT)
        assert len(worker_threads("monitor")) == 1
    assert ctrl.cleanup()
    assert not worker_threads("monitor")
