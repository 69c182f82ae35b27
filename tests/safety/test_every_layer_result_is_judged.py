"""rocoma_can/adapters.py: every callback result of every layer is judged inside the adapter's
guard: only True is success, a result that cannot even be judged or printed never escapes into the
cycle; and a lower layer never starts from the failed layer's command."""
from __future__ import annotations

import logging
import threading

import numpy as np
import pytest
from fixtures.manager_probes import (
    LAYER_METHODS,
    CommandLog,
    EmergencyProbe,
    FailproofProbe,
    Journal,
    Probe,
    layered_manager,
)

from rocoma_can import ControllerManager, ManagerState, SwitchResult

OK, FAILPROOF = ManagerState.OK, ManagerState.FAILPROOF


# --- every callback result is judged inside the adapter's guard --------------------------------
class NoTruthValue:
    """A result that cannot even be judged or printed: its __bool__ and __repr__ raise."""

    def __bool__(self) -> bool:
        raise RuntimeError("no truth value")

    def __repr__(self) -> str:
        raise RuntimeError("no repr either")


BAD_RESULTS = {"none": None, "false": False, "one": 1, "non-empty-list": ["ok"],
               "numpy-array": np.array([True, False]), "no-truth-value": NoTruthValue()}
# get_swap_state returns a state, the failproof advance nothing: every other call is judged
JUDGED_CALLS = [lm for lm in LAYER_METHODS
                if lm not in (("controller", "get_swap_state"), ("failproof", "advance"))]


@pytest.mark.parametrize("result", list(BAD_RESULTS.values()), ids=list(BAD_RESULTS))
@pytest.mark.parametrize("layer,method", JUDGED_CALLS, ids=[f"{a}.{b}" for a, b in JUDGED_CALLS])
def test_only_true_is_success_and_nothing_escapes(layer, method, result, caplog):
    """Whatever a callback returns, only True is success; anything else is that call's
    failure, handled as rocoma does (the same as a raise): nothing escapes update(), the
    switcher, the stoppers or shutdown, every e-stop ends in FAILPROOF, no thread is left."""
    mgr, added = layered_manager(layer, returns={method: result})
    if (layer, method) == ("controller", "create"):
        assert not added and mgr.available_controllers() == ["b"]
    else:
        switched = mgr.switch_controller("a")
        assert switched == (SwitchResult.ERROR if method == "initialize" else SwitchResult.SWITCHED)
        states = [mgr.update() for _ in range(3)]
        if (layer, method) == ("controller", "advance"):  # fails at once: never commands
            assert states[0] is not OK
        mgr.emergency_stop()
        mgr.update()
        mgr.emergency_stop()
        assert mgr.update() is FAILPROOF
        assert mgr.switch_controller("b") == SwitchResult.SWITCHED  # the switcher survived
        assert mgr.update() is OK
    with caplog.at_level(logging.ERROR, logger="rocoma_can.manager"):
        assert mgr.shutdown() == (method != "cleanup")  # a failed cleanup is reported
    assert "must return True" in caplog.text
    assert not [t for t in threading.enumerate() if t.name.startswith("rocoma/")]
    assert mgr.internal_errors == 0


# --- a lower layer never inherits the failed layer's command ----------------------------------
def test_a_failing_reset_command_falls_through_to_failproof():
    """reset_command (the hardware's neutral command) runs on every fall; if it raises, the
    emergency controller would start from the failed controller's command: FAILPROOF."""
    journal = Journal(update_thread=threading.get_ident())
    resets: list[object] = []

    def reset(command) -> None:
        resets.append(command)
        raise RuntimeError("reset_command broken")
    mgr = ControllerManager(FailproofProbe("failproof", journal), dt=0.001, timing=None,
                            command=CommandLog(), reset_command=reset)
    mgr.add_controller(Probe("a", journal, fail={"advance"}),
                       emergency=EmergencyProbe("e", journal))
    try:
        assert mgr.switch_controller("a") == SwitchResult.SWITCHED
        assert mgr.update() is FAILPROOF
        assert len(resets) == 1 and mgr.internal_errors == 1
        assert not journal.of("e", "initialize_fast")
    finally:
        assert mgr.shutdown()
