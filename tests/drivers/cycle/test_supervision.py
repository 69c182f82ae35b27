"""Supervisor (drivers/cycle/supervision.py) as the pure state machine it is, without a bus: which
symptom becomes a fault event, when, and only once per drive until recovery."""
from __future__ import annotations

import math

import numpy as np
import pytest
from fixtures.driver_rig import drive_configs

from rocoma_can.drivers.cycle.supervision import Supervisor
from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia301 import NmtState
from rocoma_can.drivers.protocol.cia402 import State402

TPDO_CYCLES = 3
FACTOR = 2.5
HEARTBEAT = 0.1  # drive_configs' heartbeat_ms default 100
DEADLINE = FACTOR * HEARTBEAT


def supervisor(armed: bool = True) -> Supervisor:
    sup = Supervisor(drive_configs((1, 2)), TPDO_CYCLES, FACTOR)
    if armed:
        sup.arm(0, 0.0)
        sup.arm(1, 0.0)
    return sup


def tick(sup: Supervisor, now: float, complete=(True, True),
         states=(State402.OPERATION_ENABLED,) * 2, codes=(0, 0)) -> list[str]:
    sup.tick(now, np.array(complete), np.array([int(s) for s in states]), np.array(codes))
    return [f"{e.drive}: {e.cause}" for e in sup.take_pending()]


def test_nothing_is_supervised_before_arm():
    sup = supervisor(armed=False)
    assert tick(sup, 100.0, complete=(False, False), states=(State402.FAULT,) * 2) == []
    sup.on_emcy(0, cia301.EMCY_OVERCURRENT, 1.0)
    sup.on_heartbeat(0, NmtState.STOPPED, 1.0)
    assert sup.take_pending() == []


def test_heartbeat_deadline_counts_from_the_last_heartbeat_once_per_loss():
    sup = supervisor()
    sup.on_heartbeat(0, NmtState.OPERATIONAL, 0.1)
    sup.on_heartbeat(1, NmtState.OPERATIONAL, 0.2)
    assert tick(sup, 0.1 + DEADLINE - 1e-6) == []
    assert tick(sup, 0.1 + DEADLINE + 1e-6) == [f"j1: heartbeat lost (none for {DEADLINE:.3f} s)"]
    assert tick(sup, 0.2 + DEADLINE + 1e-6) == [f"j2: heartbeat lost (none for {DEADLINE:.3f} s)"]
    assert tick(sup, 10.0) == []  # latched: one event per drive


def test_tpdos_missing_for_k_cycles_and_a_complete_cycle_resets_the_count():
    sup = supervisor()
    for t in range(TPDO_CYCLES - 1):
        assert tick(sup, 0.01 * t, complete=(False, True)) == []
    assert tick(sup, 0.03, complete=(True, True)) == []  # reset
    for t in range(TPDO_CYCLES - 1):
        assert tick(sup, 0.04 + 0.01 * t, complete=(False, True)) == []
    assert tick(sup, 0.07, complete=(False, True)) == [
        f"j1: TPDOs missing for {TPDO_CYCLES} cycles"]


@pytest.mark.parametrize("state,code,cause", [
    (State402.FAULT, cia301.EMCY_OVERCURRENT, "statusword fault bit, EMCY 0x2310 (overcurrent)"),
    (State402.FAULT_REACTION_ACTIVE, 0, "statusword fault bit"),
    (State402.UNKNOWN, 0, "statusword matches no CiA 402 state (garbled?)"),
])
def test_a_statusword_fault_or_garble_is_a_fault(state, code, cause):
    sup = supervisor()
    events = tick(sup, 0.0, states=(State402.OPERATION_ENABLED, state), codes=(0, code))
    assert events == [f"j2: {cause}"]
    assert sup.latched[1] is not None and sup.latched[1].code == code


def test_heartbeat_in_another_nmt_state_and_emcy_are_faults_at_once():
    sup = supervisor()
    sup.on_heartbeat(0, NmtState.PRE_OPERATIONAL, 0.0)
    sup.on_emcy(1, cia301.EMCY_NO_ERROR, 0.0)  # an error reset is no fault
    sup.on_emcy(1, cia301.EMCY_OVERTEMPERATURE, 0.0)
    assert [(e.drive, e.cause) for e in sup.take_pending()] == [
        ("j1", "NMT state PRE-OPERATIONAL reported in heartbeat"),
        ("j2", "EMCY 0x4310 (overtemperature)")]


def test_one_event_per_drive_later_causes_only_in_the_history():
    sup = supervisor()
    sup.on_emcy(0, cia301.EMCY_OVERCURRENT, 0.0)
    sup.on_bad_tpdo(0, 0x181, 3, 8, 0.0)
    assert len(sup.take_pending()) == 1
    assert [e.cause for e in sup.history] == [
        "EMCY 0x2310 (overcurrent)", "TPDO 0x181 with 3 bytes, its mapping has 8"]
    assert tick(sup, 0.0, states=(State402.FAULT, State402.OPERATION_ENABLED)) == []


def test_clear_watches_again_and_disarm_stops_watching():
    sup = supervisor()
    sup.on_emcy(0, cia301.EMCY_GENERIC, 0.0)
    sup.take_pending()
    sup.clear(0)
    assert tick(sup, 0.0, states=(State402.FAULT, State402.OPERATION_ENABLED)) == [
        "j1: statusword fault bit"]
    sup.disarm(1)
    assert sup.heartbeat_deadline[1] == math.inf
    assert tick(sup, 100.0, complete=(True, False), states=(State402.FAULT,) * 2) == []


def test_a_bus_fault_is_one_event_until_cleared():
    sup = supervisor()
    sup.bus_fault("CAN bus-off", 1.0)
    sup.bus_fault("CAN bus-off again", 2.0)
    events = sup.take_pending()
    assert [(e.node_id, e.cause) for e in events] == [(0, "CAN bus-off")]
    assert sup.bus_latched is events[0] and len(sup.history) == 2


@pytest.mark.parametrize("cycles,factor", [(0, 2.5), (3, 1.0)])
def test_margins_that_always_trip_are_refused(cycles, factor):
    with pytest.raises(ValueError):
        Supervisor(drive_configs((1,)), cycles, factor)
