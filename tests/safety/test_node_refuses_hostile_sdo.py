"""rocoma_can/node/server.py, objects.py: the manager node's services refuse what they cannot honour
(an e-stop COB-ID out of range, a switch name that is not UTF-8, an aborted or oversized segmented
write), and every form an e-stop may come in (a remote frame, an expedited write without size)
e-stops."""
from __future__ import annotations

import logging
import struct
import time

import can
import pytest
from fixtures.driver_rig import MANAGER_NODE_ID
from fixtures.node_rig import ESTOP_COB as SERVICE_ESTOP
from safety_rig import SAFETY, SDO_RX, sdo_exchange

from rocoma_can.errors import Refused
from rocoma_can.node.client import ManagerClient
from rocoma_can.node.objects import (
    ABORT_NOT_FOUND,
    ABORT_REFUSED,
    ABORT_TOO_LONG,
    MAX_DOWNLOAD,
)


# --- the manager node's services refuse what they cannot honour -----------------------------
@pytest.mark.parametrize("value", [0x800, 0x7FFFFFFF, 0x40000000])
def test_estop_cob_id_out_of_range_is_refused_never_masked(service, value):
    service.manager.failproof_stop()  # a stopped manager: changing it is allowed
    assert service.wait_state(0)
    with pytest.raises(Refused) as refused:
        service.client.write(0x2130, value)
    assert refused.value.code == ABORT_NOT_FOUND
    assert service.node.estop_cob_id == SERVICE_ESTOP  # unchanged: the CAN e-stop still works


def test_estop_cob_id_changes_only_while_stopped_or_latched(service, caplog):
    assert service.client.switch("pd") == 0
    with pytest.raises(Refused) as refused:
        service.client.write(0x2130, 0x0B0)
    assert refused.value.code == ABORT_REFUSED and service.node.estop_cob_id == SERVICE_ESTOP
    service.client.write(0x2111, 1)  # failproof stop
    assert service.wait_state(0)
    with caplog.at_level(logging.WARNING, logger="rocoma_can.node.server"):
        service.client.write(0x2130, 0x0B0)
    assert service.node.estop_cob_id == 0x0B0 and "e-stop COB-ID changed" in caplog.text
    service.client.write(0x2130, 0x80000000)  # bit 31: not valid = off
    assert service.node.estop_cob_id == 0


def test_switch_name_that_is_not_utf8_is_refused(service):
    """b"p\xffd" used to be decoded with errors ignored, as "pd", and switched."""
    name = b"p\xffd"
    answer = sdo_exchange(service.raw, bytes([0x21, 0x00, 0x21, 0x00, len(name), 0, 0, 0]))
    assert answer[0] == 0x60  # segmented download initiated
    answer = sdo_exchange(service.raw,
                           bytes([(7 - len(name)) << 1 | 1]) + name.ljust(7, b"\x00"))
    assert answer[0] == 0x80 and struct.unpack_from("<I", answer, 4)[0] == ABORT_NOT_FOUND
    assert service.manager.active_controller_name == "torque_off"


def test_aborted_segmented_write_never_takes_effect(service):
    bus = service.raw
    name = b"pd"
    answer = sdo_exchange(bus, bytes([0x21, 0x00, 0x21, 0x00, len(name), 0, 0, 0]))
    assert answer[0] == 0x60
    # the client aborts the transfer, then a stray last segment arrives
    bus.send(can.Message(arbitration_id=SDO_RX, is_extended_id=False,
                         data=bytes([0x80, 0x00, 0x21, 0x00]) + struct.pack("<I", 0x08000000)))
    answer = sdo_exchange(bus, bytes([(7 - len(name)) << 1 | 1]) + name.ljust(7, b"\x00"))
    assert answer[0] == 0x80  # refused: no download is open
    time.sleep(0.2)
    assert service.manager.active_controller_name == "torque_off"


def test_an_sdo_download_longer_than_any_name_is_aborted_as_it_comes(service, bus_factory):
    """A sender streaming segments for ever (or announcing 100 kB) is aborted 0x06070012 at
    MAX_DOWNLOAD bytes, never buffered on and never echoed back; the node serves on."""
    announce = bytes([0x21, 0x00, 0x21, 0x00]) + struct.pack("<I", 100_000)
    answer = sdo_exchange(service.raw, announce)
    assert answer[0] == 0x80 and struct.unpack_from("<I", answer, 4)[0] == ABORT_TOO_LONG
    answer = sdo_exchange(service.raw, bytes([0x20, 0x00, 0x21, 0x00, 0, 0, 0, 0]))  # no size
    assert answer[0] == 0x60
    toggle, sent = 0, 0
    while True:
        answer = sdo_exchange(service.raw, bytes([toggle << 4]) + b"x" * 7)
        if answer[0] == 0x80:
            break
        assert answer[0] == 0x20 | toggle << 4, answer.hex()
        toggle, sent = toggle ^ 1, sent + 7
    assert struct.unpack_from("<I", answer, 4)[0] == ABORT_TOO_LONG
    assert sent <= MAX_DOWNLOAD < sent + 7  # aborted at the limit, not later
    assert service.manager.active_controller_name == "torque_off"
    # the node serves on: a client of its own (service.client's bus saw the raw exchange,
    # and its reader may hand the last abort over late, as if it answered this switch)
    with ManagerClient(bus_factory(), MANAGER_NODE_ID, timeout=SAFETY.stall) as client:
        assert client.switch("pd") == 0


def test_remote_frame_on_the_estop_cob_id_estops(service):
    assert service.client.switch("pd") == 0
    service.client.bus.send(can.Message(arbitration_id=SERVICE_ESTOP, is_extended_id=False,
                                        is_remote_frame=True, dlc=0))
    assert service.wait_state(1)  # EMERGENCY: the smart stop runs


def test_expedited_estop_without_size_indicated_estops(service):
    assert service.client.switch("pd") == 0
    answer = sdo_exchange(service.raw, bytes([0x22, 0x10, 0x21, 0x00, 1, 0, 0, 0]))
    assert answer[0] == 0x60, answer.hex()  # accepted
    assert service.wait_state(1)
