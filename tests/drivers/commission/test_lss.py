"""`rocoma-can lss` and `scan --lss` (drivers/commission/lss.py) against LSS answers no CiA 305
slave sends (empty, cut short, another service's) and against a node id that is already taken:
one clear line and the exit code docs/cli.md gives, never a traceback, and nothing assigned
where a node already is. Over python-can's virtual bus, with simulated drives and with an
LSS slave that answers as a broken device would (fixtures/odd_node.py)."""
from __future__ import annotations

from collections.abc import Callable, Iterator

import canopen
import pytest
from fixtures.budgets import STALL
from fixtures.odd_node import OddLss, OddNode
from fixtures.running import wait_for
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rocoma_can.cli.main import main
from rocoma_can.drivers.commission import lss as lss_module
from rocoma_can.drivers.commission.lss import LSS_REQUEST, UNCONFIGURED, assign, find_unconfigured
from rocoma_can.drivers.files.identity import Identity
from rocoma_can.errors import LssFailed

BLANK = Identity(serial=0x11)  # an unconfigured simulated node
ODD = Identity(vendor_id=1, product_code=2, revision=3, serial=4)  # the odd slave's address
CS_SELECTIVE_SERIAL, CS_SELECTIVE_ANSWER = 0x43, 0x44
CS_CONFIGURE_NODE_ID, CS_BIT_TIMING, CS_STORE, CS_INQUIRE_NODE_ID = 0x11, 0x13, 0x17, 0x5E
CS_FAST_SCAN, CS_IDENTIFY_SLAVE = 0x51, 0x4F


def good(request: bytes) -> list[bytes]:
    """What a well-behaved slave at ODD (and the only unconfigured one, address 0.0.0.0 to a
    fastscan: every bit matches) answers."""
    cs = request[0]
    if cs == CS_SELECTIVE_SERIAL:
        return [bytes((CS_SELECTIVE_ANSWER,)).ljust(8, b"\0")]
    if cs in (CS_CONFIGURE_NODE_ID, CS_BIT_TIMING, CS_STORE):
        return [bytes((cs, 0)).ljust(8, b"\0")]
    if cs == CS_INQUIRE_NODE_ID:
        return [bytes((cs, UNCONFIGURED)).ljust(8, b"\0")]
    if cs == CS_FAST_SCAN:
        return [bytes((CS_IDENTIFY_SLAVE,)).ljust(8, b"\0")]
    return []


def spoiled(step: int, at: int, garbage: bytes) -> Callable[[bytes], list[bytes]]:
    """``good``, but the ``at``-th answer to requests of command ``step`` is ``garbage``."""
    seen = [0]

    def answer(request: bytes) -> list[bytes]:
        if request[0] == step:
            seen[0] += 1
            if seen[0] == at + 1:
                return [garbage]
        return good(request)
    return answer


@pytest.fixture
def no_pauses(monkeypatch):
    """The odd slave needs none of the pauses real devices get between requests."""
    monkeypatch.setattr(lss_module, "SELECTIVE_PAUSE", 0.0)
    monkeypatch.setattr(lss_module, "FASTSCAN_PAUSE", 0.0)


@pytest.fixture
def network(bus_factory) -> Iterator[canopen.Network]:
    net = canopen.Network(bus_factory())
    net.connect()
    yield net
    net.disconnect()


@pytest.fixture
def odd_lss(virtual_channel) -> Iterator[Callable[..., OddLss]]:
    slaves: list[OddLss] = []

    def start(answer: Callable[[bytes], list[bytes]]) -> OddLss:
        slaves.append(OddLss(virtual_channel, answer))
        return slaves[-1]
    yield start
    for slave in slaves:
        slave.close()


def _bus(channel: str) -> list[str]:
    return ["--interface", "virtual", "--channel", channel, "--timeout", f"{STALL / 4:g}"]


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# --- garbage answers (item: struct.error tracebacks) ----------------------------------------
def test_scan_lss_with_an_empty_answer_is_one_line_and_exit_1(odd_lss, virtual_channel,
                                                             capsys, no_pauses):
    odd_lss(lambda request: [b""] if request[0] == CS_FAST_SCAN else [])
    assert main(["scan", *_bus(virtual_channel), "--listen", "0.05", "--lss"]) == 1
    assert _one_line(capsys.readouterr().err) == (
        "rocoma-can: scan --lss: LSS fastscan: a malformed answer on 0x7E4: 0 bytes; CiA 305 "
        "answers with 8 bytes beginning 0x4F: is another device answering LSS?")


def test_lss_with_a_one_byte_answer_to_configure_node_id_is_one_line_and_exit_1(
        odd_lss, virtual_channel, capsys, no_pauses):
    odd_lss(spoiled(CS_CONFIGURE_NODE_ID, 0, b"\x11"))
    assert main(["lss", *_bus(virtual_channel), "--listen", "0.05", "--vendor", "1",
                 "--product", "2", "--revision", "3", "--serial", "4",
                 "--set-node-id", "6"]) == 1
    assert _one_line(capsys.readouterr().err) == (
        "rocoma-can: LSS configure node id 6: a malformed answer on 0x7E4: 1 byte (11); CiA "
        "305 answers with 8 bytes beginning 0x11: is another device answering LSS? (for "
        "vendor_id 0x00000001, product_code 0x00000002, revision 0x00000003, serial "
        "0x00000004)")


def _back_to_waiting(slave: OddLss) -> None:
    """Every node switched back to waiting, whatever failed: the last request the slave
    gets (it reads on a thread of its own)."""
    wait_for(lambda: slave.requests and slave.requests[-1][:2] == bytes(
        (0x04, lss_module.WAITING)), "switch state global: waiting", STALL)


GARBAGE = st.one_of(st.binary(max_size=7),  # cut short, empty
                    st.binary(min_size=8, max_size=8).filter(lambda b: b[0] not in (
                        CS_SELECTIVE_ANSWER, CS_CONFIGURE_NODE_ID, CS_BIT_TIMING, CS_STORE,
                        CS_IDENTIFY_SLAVE)))  # another service's answer


@settings(max_examples=40, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(step=st.sampled_from([CS_SELECTIVE_SERIAL, CS_CONFIGURE_NODE_ID, CS_BIT_TIMING,
                             CS_STORE]), garbage=GARBAGE)
def test_any_garbage_answer_to_any_step_of_an_assignment_is_named(
        odd_lss, network, no_pauses, step, garbage):
    slave = odd_lss(spoiled(step, 0, garbage))
    try:
        with pytest.raises(LssFailed) as failed:
            assign(network, 6, ODD, bitrate=500_000, store=True, timeout=STALL / 4)
        text = str(failed.value)
        assert "a malformed answer on 0x7E4" in text and "\n" not in text, text
        assert (f"{len(garbage)} byte" in text) and garbage.hex(" ").upper() in text
        _back_to_waiting(slave)
    finally:
        slave.close()


@settings(max_examples=25, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(at=st.integers(0, 132), garbage=GARBAGE)
def test_any_garbage_answer_anywhere_in_a_fastscan_is_named(odd_lss, network, no_pauses, at,
                                                            garbage):
    """A fastscan is 133 requests here (every bit answered); any one answer spoiled."""
    slave = odd_lss(spoiled(CS_FAST_SCAN, at, garbage))
    try:
        with pytest.raises(LssFailed, match=r"^LSS fastscan: a malformed answer on 0x7E4"):
            find_unconfigured(network, timeout=STALL / 4, limit=1)
        _back_to_waiting(slave)
    finally:
        slave.close()


def test_a_well_behaved_slave_is_still_found_and_assigned(odd_lss, network, no_pauses):
    """The same slave without garbage: the rule judges answers, it does not refuse them."""
    odd_lss(good)
    assert find_unconfigured(network, timeout=STALL / 4, limit=1) == [Identity(0, 0, 0, 0)]
    assert assign(network, 6, ODD, bitrate=500_000, store=True, timeout=STALL / 4) == ODD


def test_a_refusal_is_said_with_what_the_node_said(odd_lss, network, no_pauses):
    odd_lss(lambda r: [bytes((CS_BIT_TIMING, 1)).ljust(8, b"\0")] if r[0] == CS_BIT_TIMING
            else good(r))
    with pytest.raises(LssFailed, match=r"^LSS configure bit timing 500000: refused by the "
                                        r"node \(bit timing not supported\) \(for vendor"):
        assign(network, 6, ODD, bitrate=500_000, timeout=STALL / 4)


# --- a node id already taken (item: two nodes at one id) ------------------------------------
def test_lss_fastscan_refuses_a_node_id_a_node_already_has_before_any_lss(
        sim_segment_factory, virtual_channel, frame_recorder, capsys):
    recorder = frame_recorder()
    segment = sim_segment_factory([1], unconfigured=[BLANK])
    mark = recorder.mark()
    assert main(["lss", *_bus(virtual_channel), "--fastscan", "--set-node-id", "1"]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("rocoma-can: LSS: node id 1 is taken: node 1 is already on the "
                           "bus ("), line
    assert line.endswith("); nothing was assigned (give another id, or move that node "
                         "first)"), line
    assert not recorder.frames(LSS_REQUEST, since=mark)  # not one LSS request
    assert list(segment.drives) == [1]  # the blank node still has no node id
    # and a free id is given as before
    assert main(["lss", *_bus(virtual_channel), "--fastscan", "--set-node-id", "9"]) == 0
    assert sorted(segment.drives) == [1, 9]


def test_a_node_seen_only_by_its_sdo_answer_takes_the_id_too(virtual_channel, capsys):
    """No heartbeat heard: the SDO probe of 0x1000 finds it (any answer, garbage too)."""
    node = OddNode(virtual_channel, lambda request: [b"\x80\x00\x10\x00\x00"])
    try:
        assert main(["lss", *_bus(virtual_channel), "--listen", "0.05", "--fastscan",
                     "--set-node-id", str(OddNode.NODE)]) == 1
    finally:
        node.close()
    assert _one_line(capsys.readouterr().err) == (
        f"rocoma-can: LSS: node id {OddNode.NODE} is taken: node {OddNode.NODE} is already on "
        f"the bus (it answered an SDO upload of 0x1000 on 0x58{OddNode.NODE}); nothing was "
        "assigned (give another id, or move that node first)")


IDENTITIES = {2: Identity(vendor_id=0x9A, product_code=0x10, revision=0x2, serial=0x1002),
              3: Identity(vendor_id=0x9A, product_code=0x20, revision=0x1, serial=0x0B0B)}


def _address(i: Identity) -> list[str]:
    return ["--vendor", hex(i.vendor_id or 0), "--product", hex(i.product_code or 0),
            "--revision", str(i.revision), "--serial", hex(i.serial or 0)]


def test_by_address_the_node_that_holds_the_id_may_be_given_it_again(sim_bench,
                                                                    virtual_channel, capsys):
    bench = sim_bench([2, 3], identities=IDENTITIES)
    assert main(["lss", *_bus(virtual_channel), *_address(IDENTITIES[2]),
                 "--set-node-id", "2", "--store"]) == 0
    assert "node id 2, stored" in capsys.readouterr().out
    # another node's address to an id node 2 holds: refused, node 3 keeps its own
    assert main(["lss", *_bus(virtual_channel), *_address(IDENTITIES[3]),
                 "--set-node-id", "2"]) == 1
    assert "node id 2 is taken: node 2 is already on the bus" in capsys.readouterr().err
    assert sorted(bench.segment.drives) == [2, 3]
    (three,) = [s for s in bench.segment.lss_slaves if s.identity == IDENTITIES[3]]
    assert three.active_id == three.pending_id == 3


def test_present_says_how_a_node_was_seen(sim_segment_factory, network):
    from rocoma_can.drivers.commission.scan import present
    sim_segment_factory([4])
    assert present(network, 5, listen=0.05, timeout=STALL / 4) is None
    seen = present(network, 4, listen=0.05, timeout=STALL / 4)
    assert seen is not None and ("0x704" in seen or "0x584" in seen), seen


def test_lss_help_names_the_listen_option(capsys):
    with pytest.raises(SystemExit):
        main(["lss", "--help"])
    assert "--listen S" in capsys.readouterr().out
