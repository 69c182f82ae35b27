"""DriveBringup (drivers/bringup/drive_bringup.py), the per-drive start-up state machine,
without a bus: its phases, timeouts and failure causes. The SDO configuration job is replaced
by its result (the job itself is tested on the bus:
tests/drivers/bringup/test_driver_bus_bring_up.py); jobs run inline."""
from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any

import canopen
import pytest
from fixtures.driver_rig import drive_configs

from rocoma_can.drivers.bringup import drive_bringup as bringup
from rocoma_can.drivers.bringup.configure import ConfigResult
from rocoma_can.drivers.bringup.drive_bringup import BringupPhase, DriveBringup
from rocoma_can.drivers.plan.config import Timeouts
from rocoma_can.drivers.plan.drive_plan import plan_drive
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402

TIMEOUTS = Timeouts(boot_wait=1.0, start=2.0, reset=1.0, enable=1.0)
SWITCH_ON_DISABLED = 0x0040
FAULT = 0x0008


class Inline(Executor):
    """Runs every job at submit: the state machine's view of a worker that is done."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        future: Future[Any] = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - the job's failure is its result
            future.set_exception(exc)
        return future


@pytest.fixture
def drive(monkeypatch):
    results: list[Any] = [ConfigResult(SWITCH_ON_DISABLED, 0)]

    def configure(*args: Any) -> ConfigResult:
        result = results[0]
        if isinstance(result, Exception):
            raise result
        return result
    monkeypatch.setattr(bringup, "configure", configure)
    config = drive_configs((1,))[0]
    b = DriveBringup(plan_drive(config), canopen.RemoteNode(1, canopen.ObjectDictionary()),
                     100, 200, TIMEOUTS)
    b.results = results  # what the next configuration returns (or raises)
    b.restart(0.0)
    return b


def step(b: DriveBringup, now: float, fresh: bool = False,
         state: State402 = State402.SWITCH_ON_DISABLED, code: int = 0) -> bool:
    return b.step(now, Inline(), fresh, int(state), code)


def test_waits_for_boot_up_then_configures_starts_probes_and_is_ready_once(drive):
    assert not step(drive, 0.5) and drive.phase == BringupPhase.WAIT_BOOT
    drive.alive = True  # a boot-up or heartbeat frame arrived
    step(drive, 0.6)
    assert drive.phase == BringupPhase.CONFIGURING
    step(drive, 0.7)
    assert drive.phase == BringupPhase.STARTING and drive.mapped
    step(drive, 0.8, fresh=True)
    assert drive.phase == BringupPhase.PROBING and drive.probing  # shutdown (0x06) goes out
    assert step(drive, 0.9, fresh=True, state=State402.READY_TO_SWITCH_ON)  # READY: once
    assert drive.phase == BringupPhase.READY and not step(drive, 1.0, fresh=True)


def test_a_silent_drive_is_probed_after_boot_wait(drive):
    step(drive, TIMEOUTS.boot_wait - 0.01)
    assert drive.phase == BringupPhase.WAIT_BOOT
    step(drive, TIMEOUTS.boot_wait)
    assert drive.phase == BringupPhase.CONFIGURING


def test_configuration_failures_and_sto_are_reported(drive):
    drive.results[0] = RuntimeError("does not answer (no SDO reply to 0x1000)")
    drive.alive = True
    step(drive, 0.0)
    step(drive, 0.1)
    assert drive.phase == BringupPhase.FAILED
    assert drive.failure == "does not answer (no SDO reply to 0x1000)"
    drive.restart(1.0)
    assert (drive.phase, drive.failure) == (BringupPhase.WAIT_BOOT, None)
    drive.results[0] = ConfigResult(FAULT, cia301.EMCY_STO)
    drive.alive = True
    step(drive, 1.0)
    step(drive, 1.1)
    assert (drive.phase, drive.failure) == (BringupPhase.FAILED,
                                            "STO input low (safe torque off active)")


def test_no_tpdo_after_nmt_start_fails_after_the_start_timeout(drive):
    drive.alive = True
    step(drive, 0.0)
    step(drive, 0.0)
    assert drive.phase == BringupPhase.STARTING
    step(drive, TIMEOUTS.start)
    assert drive.phase == BringupPhase.STARTING
    step(drive, TIMEOUTS.start + 0.01)
    assert drive.phase == BringupPhase.FAILED
    assert "no TPDO within 2.0 s of NMT start" in drive.failure


def test_a_faulted_drive_gets_a_reset_edge_then_probes(drive):
    drive.alive = True
    step(drive, 0.0)
    step(drive, 0.0)
    step(drive, 0.1, fresh=True, state=State402.FAULT)
    assert drive.phase == BringupPhase.RESETTING and not drive.fault_reset_bit  # bit 7 low first
    step(drive, 0.11, fresh=True, state=State402.FAULT)
    assert drive.fault_reset_bit  # then high: the rising edge
    step(drive, 0.12, fresh=True, state=State402.FAULT)
    step(drive, 0.13, fresh=True, state=State402.SWITCH_ON_DISABLED)
    assert drive.phase == BringupPhase.PROBING


def test_a_fault_that_persists_and_a_refused_shutdown_fail_with_the_reason(drive):
    drive.alive = True
    step(drive, 0.0)
    step(drive, 0.0)
    step(drive, 0.1, fresh=True, state=State402.FAULT, code=cia301.EMCY_OVERCURRENT)
    step(drive, 0.1 + TIMEOUTS.reset + 0.01, fresh=True, state=State402.FAULT,
         code=cia301.EMCY_OVERCURRENT)
    assert drive.phase == BringupPhase.FAILED
    assert drive.failure == "fault persists after fault reset (error code 0x2310)"

    drive.restart(10.0, probe_at_once=True)
    step(drive, 10.0)
    step(drive, 10.0)
    step(drive, 10.1, fresh=True)  # -> PROBING
    step(drive, 10.1 + TIMEOUTS.reset + 0.01, fresh=True)  # still switch on disabled
    assert drive.phase == BringupPhase.FAILED and "refuses shutdown" in drive.failure
