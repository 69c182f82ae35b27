"""drivers/sim/lss.py: the simulated nodes' LSS slaves (CiA 305), service by service, driven over
the bus by canopen's LssMaster (the reference master); answers checked on the frames too. Runs on
the virtual bus and on vcan0."""
from __future__ import annotations

import pytest
from canopen import lss as cs
from canopen.lss import LssError, LssMaster
from fixtures.paths import TESTS

from rocoma_can.drivers.commission.lss import LSS_RESPONSE, UNCONFIGURED
from rocoma_can.drivers.files.identity import Identity
from rocoma_can.drivers.protocol import cia301

CONFIGURED = Identity(vendor_id=0x9A, product_code=0x10, revision=0x20003, serial=0x1001)
#: few one bits: each costs a fastscan one unanswered request (a whole timeout)
BLANK = Identity(vendor_id=0x9A, product_code=0x10, revision=0x20000, serial=0x1000)


@pytest.fixture
def bench(sim_bench, sim_interface):
    bench = sim_bench([3], sim_interface, identities={3: CONFIGURED}, unconfigured=[BLANK])
    lss: LssMaster = bench.network.lss
    lss.RESPONSE_TIMEOUT = bench.within(0.01)  # an answer is due at once
    return bench


def address(identity: Identity) -> tuple[int, int, int, int]:
    return (identity.vendor_id, identity.product_code, identity.revision, identity.serial)


def test_switch_selective_then_inquire_and_configure(bench):
    lss = bench.network.lss
    assert lss.send_switch_state_selective(*address(CONFIGURED))
    # only the selected node is in configuration state: one answer each
    for command, value in ((cs.CS_INQUIRE_VENDOR_ID, 0x9A), (cs.CS_INQUIRE_PRODUCT_CODE, 0x10),
                           (cs.CS_INQUIRE_REVISION_NUMBER, 0x20003),
                           (cs.CS_INQUIRE_SERIAL_NUMBER, 0x1001)):
        assert lss.inquire_lss_address(command) == value
    assert lss.inquire_node_id() == 3
    with pytest.raises(LssError, match="LSS Error: 1"):
        lss.configure_node_id(0x80)  # not a node id: refused
    with pytest.raises(LssError, match="LSS Error: 1"):
        lss.configure_bit_timing(5)  # reserved in the CiA 305 table
    lss.configure_bit_timing(2)  # 500 kbit/s
    lss.configure_node_id(8)
    lss.store_configuration()
    slave = next(s for s in bench.segment.lss_slaves if s.address == address(CONFIGURED))
    assert (slave.pending_id, slave.stored_id, slave.active_id) == (8, 8, 3)
    assert slave.stored_bit_timing == 2
    lss.send_switch_state_global(LssMaster.WAITING_STATE)
    # a configured node keeps its id until a reset; in waiting state it answers no inquiry
    with pytest.raises(LssError, match="No LSS response"):
        lss.inquire_node_id()
    assert list(bench.segment.drives) == [3]
    bench.nmt(cia301.NmtCommand.RESET_NODE, 3)  # the stored id
    assert list(bench.segment.drives) == [8]
    assert bench.recorder.wait_for_count(1, bench.within(0.1), cob_id=cia301.HEARTBEAT + 8,
                                         where=lambda f: f.data == b"\x00")


def test_a_wrong_address_selects_nobody(bench):
    lss = bench.network.lss
    vendor, product, revision, serial = address(CONFIGURED)
    with pytest.raises(LssError, match="No LSS response"):
        lss.send_switch_state_selective(vendor, product, revision, serial + 1)
    with pytest.raises(LssError, match="No LSS response"):
        lss.inquire_node_id()


def test_identify_remote_slave_by_range_and_non_configured(bench):
    lss = bench.network.lss
    mark = bench.recorder.mark()
    # both nodes lie in this range: two answers
    lss.send_identify_remote_slave(0x9A, 0x10, 0x20000, 0x2FFFF, 0x1000, 0x1001)
    lss.send_identify_remote_slave(0x9A, 0x10, 0x20000, 0x2FFFF, 0x1002, 0x2001)  # none
    lss.send_identify_non_configured_remote_slave()  # the unconfigured node only
    answers = bench.recorder.wait_for_count(3, bench.within(0.01), cob_id=LSS_RESPONSE,
                                            since=mark)
    assert [f.data[0] for f in answers] == [cs.CS_IDENTIFY_SLAVE] * 2 + [
        cs.CS_IDENTIFY_NON_CONFIGURED_SLAVE]


def test_fastscan_finds_the_unconfigured_node_which_boots_with_its_new_id(bench):
    lss = bench.network.lss
    mark = bench.recorder.mark()
    assert lss.fast_scan() == (True, list(address(BLANK)))
    # it alone is in configuration state now
    assert lss.inquire_node_id() == UNCONFIGURED
    assert lss.fast_scan() == (False, None)  # no other unconfigured node in waiting state
    lss.configure_node_id(12)
    lss.send_switch_state_global(LssMaster.WAITING_STATE)  # unconfigured: starts at once
    assert bench.recorder.wait_for_count(1, bench.within(0.1), cob_id=cia301.HEARTBEAT + 12,
                                         where=lambda f: f.data == b"\x00", since=mark)
    assert sorted(bench.segment.drives) == [3, 12]
    # until then the node sent nothing but LSS answers
    frames = bench.recorder.frames(since=mark)
    boot = next(k for k, f in enumerate(frames) if f.cob_id == cia301.HEARTBEAT + 12)
    assert {f.cob_id for f in frames[:boot]} <= {LSS_RESPONSE, LssMaster.LSS_TX_COBID,
                                                  cia301.HEARTBEAT + 3}
    assert bench.node(12).sdo.upload(0x1018, 4) == (0x1000).to_bytes(4, "little")


def test_reset_communication_of_a_node_with_no_pending_change_is_an_ordinary_reset(bench):
    bench.nmt(cia301.NmtCommand.RESET_COMMUNICATION, 3)
    assert list(bench.segment.drives) == [3]
    assert bench.segment.drives[3].nmt_state == cia301.NmtState.PRE_OPERATIONAL


def test_a_file_listing_the_revision_without_a_value_still_gives_every_node_an_lss_address(
        sim_bench, virtual_channel, capsys):
    """vendor_a.eds (the walk-through's file) lists 0x1018:3 without a value, which the
    drives answer as 0: that 0 is their LSS address too, so `sim --unconfigured serial=N`
    with it runs and a configured node is selectable by what `scan` shows of it."""

    from rocoma_can.cli.main import main
    vendor_a = str(TESTS / "fixtures" / "eds" / "vendor_a.eds")
    assert main(["sim", "--interface", "virtual", "--channel", virtual_channel + "-cli",
                 "--eds", vendor_a, "--unconfigured", "serial=0x5", "--duration", "0.1"]) == 0
    capsys.readouterr()
    bench = sim_bench([2], eds_path=vendor_a, unconfigured=[Identity(serial=0x5)])
    assert bench.node(2).sdo.upload(0x1018, 3) == bytes(4)
    lss = bench.network.lss
    lss.RESPONSE_TIMEOUT = bench.within(0.01)
    assert lss.send_switch_state_selective(0xAA, 0x1234, 0, 2)  # node 2 as scan shows it
    assert lss.inquire_node_id() == 2
    lss.send_switch_state_global(LssMaster.WAITING_STATE)
    blank = next(s for s in bench.segment.lss_slaves if not s.configured)
    assert blank.address == (0xAA, 0x1234, 0, 0x5)


def test_two_simulated_nodes_with_one_identity_are_a_usage_error_naming_both(
        virtual_channel, capsys):
    """`sim --nodes 1,2 --identity 1:serial=2`: node 2 has serial 2 by default, so the two
    would share an LSS address. One line naming both nodes, exit 2 (the arguments are
    wrong: nothing failed to open)."""
    from rocoma_can.cli.main import main
    assert main(["sim", "--interface", "virtual", "--channel", virtual_channel, "--nodes",
                 "1,2", "--identity", "1:serial=2", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "cannot open" not in err, err
    assert err.startswith("rocoma-can sim: node 1 and node 2 have the same identity"), err
    assert "serial 0x00000002" in err
