"""rocoma_can/cli/operator_verbs.py, rocoma_can/node/client.py: the operator's view end to end on
real SocketCAN (vcan0): `rocoma-can run` and the CLI as separate processes, the simulated drives in
this one (so a fault is injected exactly when the test wants it). A faulted drive: `clear`
unlatches, but `switch` stays refused with the reason and no drive is re-enabled; `status --json`
lists every drive's phase and fault."""
from __future__ import annotations

import json
import time

from test_e2e_manager import CONFIG, DRIVES, NODE, cli, processes, wait_for  # noqa: F401

from rocoma_can.drivers.protocol import cia301
from rocoma_can.drivers.protocol.cia402 import State402


def test_clear_does_not_rearm_a_faulted_drive(processes, frame_recorder,  # noqa: F811
                                              sim_segment_factory):
    segment = sim_segment_factory(DRIVES, interface="socketcan")
    rec = frame_recorder(interface="socketcan")
    processes("run", str(CONFIG))
    # brought up: every drive answers SYNCs with TPDO1 (NMT operational, mapped)
    wait_for(lambda: all(rec.count(0x180 + n) >= 25 for n in DRIVES), 60,
             "TPDO1 from every drive")
    mark = rec.mark()
    segment.drives[2].trip_fault(cia301.EMCY_OVERCURRENT)
    # the manager latches the fault as an e-stop: its node says so with EMCY 0x9000
    rec.wait_for(lambda f: f.cob_id == 0x80 + NODE, timeout=60, since=mark)

    assert cli("clear").returncode == 0
    switched = cli("switch", "pd")
    assert (switched.returncode, switched.stdout.strip()) == (1, "ERROR"), switched
    assert "drives not ready: j2 (fault: " in switched.stderr, switched.stderr
    time.sleep(1.0)
    assert all(d.state402 != State402.OPERATION_ENABLED for d in segment.drives.values())

    status = cli("status", "--json")
    assert status.returncode == 0, status
    report = json.loads(status.stdout)
    assert report["state"] == "FAILPROOF" and report["startup_finished"] is True
    drives = {d["node_id"]: d for d in report["drives"]}
    assert sorted(drives) == list(DRIVES)
    assert "0x2310" in drives[2]["fault"]
    assert [drives[n]["fault"] for n in (1, 3)] == [None, None]
    assert all(d["phase"] == "READY" and not d["enabled"] for d in drives.values())
