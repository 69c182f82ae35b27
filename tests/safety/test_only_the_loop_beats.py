"""drivers/cycle/frames_out.py, rocoma_can/node/server.py: only the control loop may produce the
manager's heartbeat: if anything else kept beating after the loop hung (an SDO write of 0x1017, an
NMT command to the manager's node), the drives' heartbeat consumers would never time out and 0x6007
would never switch them off. Driven over the virtual bus against simulated drives with the real
hardware layer, manager and node."""
from __future__ import annotations

import struct
import time

import pytest
from canopen.sdo.constants import ABORT_WRITE_READONLY
from canopen.sdo.exceptions import SdoAbortedError
from fixtures.driver_rig import MANAGER_NODE_ID, seconds_until_all_off
from safety_rig import SAFETY, cycle_while

from rocoma_can.drivers.protocol.cia402 import State402

NMT_START, NMT_STOP, NMT_PRE_OP, NMT_RESET_NODE, NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82


SEQUENCES = {
    "sdo-write-1017": [("sdo", 0x1017, 10)],
    "sdo-write-1017-zero-then-ten": [("sdo", 0x1017, 0), ("sdo", 0x1017, 10)],
    "nmt-reset-communication": [("nmt", NMT_RESET_COMM, MANAGER_NODE_ID)],
    "nmt-reset-node-broadcast": [("nmt", NMT_RESET_NODE, 0)],
    "nmt-pre-op-start-stop": [("nmt", NMT_PRE_OP, MANAGER_NODE_ID),
                              ("nmt", NMT_START, MANAGER_NODE_ID),
                              ("nmt", NMT_STOP, MANAGER_NODE_ID)],
    "nmt-reset-then-sdo-1017": [("nmt", NMT_RESET_COMM, 0), ("sdo", 0x1017, 5),
                                ("nmt", NMT_START, 0)],
}


@pytest.mark.parametrize("sequence", list(SEQUENCES.values()), ids=list(SEQUENCES))
def test_only_the_loop_produces_the_manager_heartbeat(served, sequence):
    segment, rig, client, network = served.segment, served.rig, served.client, served.network

    def traffic() -> None:
        for kind, a, b in sequence:
            if kind == "sdo":
                with pytest.raises(SdoAbortedError) as refused:
                    client.sdo.download(0x1017, 0, struct.pack("<H", b))
                assert refused.value.code == ABORT_WRITE_READONLY
            else:
                network.send_message(0x000, bytes((a, b)))
    cycle_while(rig, traffic)
    rig.run(10 * rig.dt)
    # the period the loop uses is what 0x1017 says
    assert struct.unpack("<H", client.sdo.upload(0x1017, 0))[0] == SAFETY.heartbeat_ms
    # the loop hangs (no more cycles): nothing else beats, every drive switches itself off
    stopped = time.monotonic()
    consumer = rig.hw.consumer_ms / 1000
    elapsed = seconds_until_all_off(segment, stopped, consumer + SAFETY.stall)
    assert elapsed <= consumer + SAFETY.stall
    assert all(d.state402 == State402.SWITCH_ON_DISABLED for d in segment.drives.values())
