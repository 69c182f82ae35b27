"""controllers/*.py (every controller): the cycle allocates no arrays: advance and initialize_fast
work in preallocated buffers.

Measured with tracemalloc as the peak memory above the baseline during the calls, once with
64 and once with 2048 joints. numpy and Python allocate a little per call whatever the size
(a reduction's iterator, floats, bound methods); a temporary array of joint values would add
its size, 15 KiB more with 2048 joints. So the peak must not grow with the number of joints.
"""
from __future__ import annotations

import tracemalloc

import pytest
from fixtures.joint_plant import JointPlant, attach

from rocoma_can.controllers.damp import Damp
from rocoma_can.controllers.float import Float
from rocoma_can.controllers.hold import Hold
from rocoma_can.controllers.pd import JointPD
from rocoma_can.controllers.quick_stop import QuickStop
from rocoma_can.controllers.torque_off import TorqueOff
from rocoma_can.controllers.trajectory import Trajectory
from rocoma_can.interfaces import EmergencyController

DT = 0.001
SIZES = (64, 2048)


def peak_growth(fn, calls: int = 20) -> int:
    fn()  # warm-up: lazy attributes, caches
    tracemalloc.start()  # the first start after a stop allocates: warm it up too
    tracemalloc.stop()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        for _ in range(calls):
            fn()
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def subset(n: int) -> list[str]:
    return [f"joint{i}" for i in range(0, n, 2)]  # not contiguous: the gather/scatter path


@pytest.mark.parametrize("make", [
    lambda n: TorqueOff(),
    lambda n: Float("float", joints=subset(n)),
    lambda n: JointPD("pd", kp=10.0, kd=1.0, target=0.3, torque_limit=5.0,
                      velocity_limit=1.0),
    lambda n: JointPD("pd_csp", joints=subset(n), target=0.3, mode="CSP", velocity_limit=1.0),
    lambda n: Trajectory("sine", amplitude=0.2, frequency=1.0, mode="CST"),
    lambda n: Trajectory("min_jerk", joints=subset(n), kind="min_jerk", target=0.5),
    lambda n: Damp("damp", damping=2.0, torque_limit=3.0),
    lambda n: Hold("hold", joints=subset(n)),
    lambda n: Hold("hold_csp", mode="CSP"),
    lambda n: QuickStop("quick_stop", torque_off_after=10.0),
], ids=lambda make: make(2).name)
def test_cycle_calls_allocate_no_arrays(make):
    peaks = {}
    for n in SIZES:
        plant = JointPlant(n)
        plant.set(0.1, 0.5)
        ctrl = attach(make(n), plant)
        assert ctrl.create(DT) is not False
        init = 0
        if isinstance(ctrl, EmergencyController):
            init = peak_growth(lambda c=ctrl: c.initialize_fast(DT))
        elif hasattr(ctrl, "initialize"):
            assert ctrl.initialize(DT)
        peaks[n] = init, peak_growth(lambda c=ctrl: c.advance(DT))
    small, large = peaks[SIZES[0]], peaks[SIZES[1]]
    assert large[0] - small[0] < 2048, peaks  # initialize_fast
    assert large[1] - small[1] < 2048, peaks  # advance


def test_the_measure_catches_a_temporary_array():
    small, large = (JointPlant(n).state.position for n in SIZES)
    assert peak_growth(lambda: large * 2.0) - peak_growth(lambda: small * 2.0) >= 15 * 1024
