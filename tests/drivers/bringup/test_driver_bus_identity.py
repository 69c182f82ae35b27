"""drivers/bringup/drive_bringup.py, drivers/files/identity.py: identity at bring-up (0x1018): a
drive that is not the one its config or its file names is refused before anything is written to it,
and the others come up.

What must hold: a drive answering the identity its config requires comes up; swapped
serial numbers (swapped node ids or cables) are refused naming both values, with no SDO
write to the refused drives; a product code other than its file's is refused without
``identity:``, and ``identity: any`` accepts it; a drive swapped while the robot runs is
caught by the recovery's bring-up; a two-axis node's identity is read once, by its lowest
axis.

The tests that take the ``can_setup`` fixture run twice: on python-can's virtual bus (fast
suite) and on SocketCAN vcan0 (vcan suite, through tools/vcan-run; see driver_rig.VCAN).
"""
from __future__ import annotations

from pathlib import Path

import pytest
from fixtures.driver_rig import VIRTUAL, Rig, bring_up, synced_mark
from fixtures.paths import TESTS

from rocoma_can import ManagerState
from rocoma_can import eds as shipped_eds
from rocoma_can.drivers.files.identity import Identity
from rocoma_can.drivers.protocol import cia301

SERIAL = 0x0000_1200  # + node id: each simulated drive's serial number
VENDOR, PRODUCT = 0x0000_009A, 0x0000_1234
TWO_AXES = str(TESTS / "fixtures" / "eds" / "two_axes.eds")


def vendor_file(tmp_path: Path) -> str:
    """The shipped generic drive's EDS as a vendor's: [DeviceInfo] names vendor 0x9A, product
    0x1234 (its 0x1018 defaults stay the generic 0 / 0x402: [DeviceInfo] is what counts)."""
    text = shipped_eds.path(shipped_eds.CIA402_DRIVE).read_text()
    text = text.replace("VendorNumber=0x00000000", f"VendorNumber=0x{VENDOR:08X}")
    text = text.replace("ProductNumber=0x00000402", f"ProductNumber=0x{PRODUCT:08X}")
    path = tmp_path / "vendor_drive.eds"
    path.write_text(text)
    return str(path)


@pytest.fixture
def drives(can_setup, virtual_channel, sim_segment_factory):
    """``drives(**kw)``: the setup's simulated drives on its bus, started (``kw``: the
    segment's, such as identities= and eds_path=)."""
    def make(**kw):
        return sim_segment_factory(can_setup.nodes, channel=can_setup.channel(virtual_channel),
                                   interface=can_setup.interface, params=can_setup.joints,
                                   sync_period=can_setup.dt, **kw)
    return make


def serials(nodes, swapped=()) -> dict[int, Identity]:
    """Each node's identity: serial SERIAL + node id, the pair ``swapped`` exchanged."""
    own = {n: SERIAL + n for n in nodes}
    if swapped:
        a, b = swapped
        own[a], own[b] = own[b], own[a]
    return {n: Identity(serial=s) for n, s in own.items()}


def sdo_writes(recorder, node: int, since: int = 0) -> int:
    """SDO download requests (client command specifier 1) sent to ``node``."""
    return recorder.count(cia301.SDO_RX + node, since, where=lambda f: f.data[0] >> 5 == 1)


def status(rig: Rig) -> dict:
    return {s.node_id: s for s in rig.hw.drive_status()}


def test_a_swapped_serial_is_refused_naming_both_values_and_the_others_come_up(
        drives, make_rig, recorder, can_setup):
    nodes = can_setup.nodes
    a, b = nodes[-2], nodes[-1]
    segment = drives(identities=serials(nodes, swapped=(a, b)))
    each = {n: {"identity": {"serial": SERIAL + n}} for n in nodes}
    rig = make_rig(each=each, required=range(len(nodes) - 2))
    bring_up(rig)
    synced_mark(recorder, rig)
    found = status(rig)
    assert all(found[n].phase == "READY" for n in nodes[:-2]), rig.hw.drive_status()
    for mine, theirs in ((a, b), (b, a)):
        assert found[mine].phase == "FAILED"
        assert found[mine].fault == (f"serial 0x{SERIAL + mine:08X} expected, "
                                     f"0x{SERIAL + theirs:08X} found: it is drive "
                                     f"'j{theirs}' (node {theirs}): swapped node ids or "
                                     "cables?")
        assert sdo_writes(recorder, mine) == 0  # refused before anything was written
        assert segment.drives[mine].nmt_state != cia301.NmtState.OPERATIONAL
    assert all(sdo_writes(recorder, n) > 0 for n in nodes[:-2])


def test_a_product_code_other_than_its_files_is_refused_without_identity(
        drives, make_rig, tmp_path, can_setup):
    nodes = can_setup.nodes
    odd, eds = nodes[-1], vendor_file(tmp_path)
    drives(eds_path=eds, identities={odd: Identity(product_code=0x77)})
    rig = make_rig(drive={"eds": eds}, required=range(len(nodes) - 1))
    bring_up(rig)
    found = status(rig)
    assert all(found[n].phase == "READY" for n in nodes if n != odd), rig.hw.drive_status()
    assert found[odd].phase == "FAILED"
    assert found[odd].fault == (
        f"vendor_id 0x{VENDOR:08X}, product_code 0x00000077 found, its file vendor_drive.eds "
        f"is for vendor_id 0x{VENDOR:08X}, product_code 0x{PRODUCT:08X}: wrong file or wrong "
        "drive?")


def test_identity_any_accepts_a_drive_its_file_is_not_for(drives, make_rig, tmp_path,
                                                           can_setup):
    nodes, eds = can_setup.nodes, vendor_file(tmp_path)
    drives(eds_path=eds, identities={n: Identity(vendor_id=0x1, product_code=0x77) for n in nodes})
    rig = make_rig(drive={"eds": eds, "identity": "any"})
    bring_up(rig)
    assert rig.hw.all_ready, rig.hw.drive_status()


def test_a_drive_swapped_while_running_is_refused_by_the_recovery(drives, make_rig,
                                                                  can_setup):
    """Another drive put in one's place boots (a heartbeat not OPERATIONAL: a fault); the
    recovery configures it again, and its identity is read again first."""
    nodes = can_setup.nodes
    segment = drives(identities=serials(nodes))
    rig = make_rig(each={n: {"identity": {"serial": SERIAL + n}} for n in nodes})
    bring_up(rig)
    assert rig.hw.all_ready, rig.hw.drive_status()
    swapped = nodes[-1]
    segment.drives[swapped].swap(Identity(serial=0x5678))
    # the swapped drive's own fault (the manager may leave OK first for another reason
    # on a loaded machine: a recovery begun then finds the swapped drive still READY)
    assert rig.run_until(lambda: rig.hw.drive_status()[-1].fault is not None,
                         rig.setup.detect_budget()), rig.hw.drive_status()
    assert rig.mgr.state != ManagerState.OK
    future = rig.hw.recover(rig.setup.recovery_budget())
    assert rig.run_until(future.done, rig.setup.recovery_budget())
    assert future.result() is False
    found = status(rig)
    assert found[swapped].phase == "FAILED"
    assert found[swapped].fault == (f"serial 0x{SERIAL + swapped:08X} expected, 0x00005678 "
                                    "found: another drive of the same model (replaced?)")
    assert all(found[n].phase == "READY" for n in nodes[:-1]), rig.hw.drive_status()


def test_a_two_axis_node_is_identified_once_by_its_lowest_axis(virtual_channel,
                                                              sim_segment_factory,
                                                              bus_factory, frame_recorder):
    segment = sim_segment_factory([1], channel=virtual_channel, eds_path=TWO_AXES,
                                  axes={1: 2}, identities={1: Identity(serial=0x5678)})
    recorder = frame_recorder(virtual_channel)
    rig = Rig.for_setup(bus_factory(virtual_channel), [1], VIRTUAL, modes=("csp", "csv"),
                        axes=(1, 2), drive={"eds": TWO_AXES,
                                            "identity": {"serial": 0x1234}})
    try:
        bring_up(rig)
        synced_mark(recorder, rig)
        first, second = rig.hw.drive_status()
        assert first.phase == second.phase == "FAILED"
        assert first.fault == ("serial 0x00001234 expected, 0x00005678 found: another drive "
                               "of the same model (replaced?)")
        assert second.fault == f"its node's axis 1 (drive 'j1') did not start: {first.fault}"
        reads = recorder.frames(cia301.SDO_RX + 1, where=lambda f: f.data[0] >> 5 == 2
                                and f.data[1:4] == bytes((0x18, 0x10, 4)))
        assert len(reads) == 1
        assert sdo_writes(recorder, 1) == 0
        assert segment.drives[1].nmt_state != cia301.NmtState.OPERATIONAL
    finally:
        rig.close()
