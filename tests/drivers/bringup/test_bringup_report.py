"""What bring-up tells a person (drivers/bringup/report.py), each thing once: a whole bus
that does not answer (unplugged, unpowered, at another bit rate) is one line for the bus
with what to check, not a line per drive and their summary; a silent drive among answering
ones is its own line; the end of the start-up is one audit line."""
from __future__ import annotations

import logging

import pytest
from fixtures.driver_rig import bring_up
from fixtures.paths import TESTS
from fixtures.running import wait_for

from rocoma_can.audit import AUDIT

HARDWARE = "rocoma_can.drivers.hardware"
FAST_SDO = 0.05  # s: a silent drive fails after 3 of them and their pauses


def said(caplog: pytest.LogCaptureFixture, logger: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == logger]


def test_a_bus_where_no_drive_answers_is_said_once_with_what_to_check(make_rig, caplog):
    rig = make_rig(nodes=(7, 8, 9), sdo_timeout=FAST_SDO)
    with caplog.at_level(logging.INFO):
        bring_up(rig)
        wait_for(lambda: said(caplog, AUDIT), "the start-up's end told", rig.setup.stall)
    channel = rig.hw.ports[0].channel
    assert said(caplog, HARDWARE) == [
        f"no drive answers on {channel}: j7 (node 7), j8 (node 8), j9 (node 9) each did not "
        f"answer (SDO 0x1000, 3 x {FAST_SDO:g} s); check that the drives have power, the bit "
        "rate (every node's and the interface's must be the same), the cable and its "
        "termination (120 ohm at both ends of the bus), and the node ids (rocoma-can scan "
        "lists what answers)"]
    [end] = said(caplog, AUDIT)
    assert end.startswith("bring-up ended in ") and end.endswith(
        ": 0 of 3 drives ready; failed: j7, j8, j9 (said above)"), end
    # each drive's status still says its own failure (status, the live view)
    assert all("did not answer (SDO 0x1000" in str(s.fault) for s in rig.hw.drive_status())


def test_a_silent_drive_among_answering_ones_is_said_as_its_own(segment, make_rig, caplog):
    nodes = tuple(segment.drives)
    rig = make_rig(nodes=nodes + (9,), sdo_timeout=FAST_SDO)  # no drive 9 on the segment
    with caplog.at_level(logging.INFO):
        bring_up(rig)
        wait_for(lambda: said(caplog, AUDIT), "the start-up's end told", rig.setup.stall)
    assert said(caplog, HARDWARE) == [
        f"drive 'j9' (node 9): start-up failed: did not answer (SDO 0x1000, 3 x {FAST_SDO:g} "
        "s): power, wiring, node id, bitrate?"]
    ready = ", ".join(f"j{n}" for n in nodes)
    [end] = said(caplog, AUDIT)
    assert end.endswith(f": {len(nodes)} of {len(nodes) + 1} drives ready ({ready}); "
                        "failed: j9 (said above)"), end


def test_a_start_up_where_every_drive_came_up_is_one_audit_line(segment, make_rig, caplog):
    nodes = tuple(segment.drives)
    rig = make_rig(nodes=nodes)
    with caplog.at_level(logging.INFO):
        bring_up(rig)
        wait_for(lambda: said(caplog, AUDIT), "the start-up's end told", rig.setup.stall)
        rig.run(0.1)  # nothing more is said while the drives stay ready
    [end] = said(caplog, AUDIT)
    assert end.startswith("bring-up finished in ") and end.endswith(
        f": {len(nodes)} drives ready ({', '.join(f'j{n}' for n in nodes)})"), end
    assert said(caplog, HARDWARE) == []


def test_plan_notes_are_said_once_for_every_drive_they_concern(make_rig, caplog, tmp_path):
    """Drives of one model share the notes of their EDS: one warning per note, naming the
    drives (it was a warning per note per drive, each start)."""
    no_abort = str(TESTS / "fixtures" / "eds" / "no_abort_option.eds")
    with caplog.at_level(logging.WARNING):
        make_rig(nodes=(1, 2, 3), drive={"eds": no_abort})
    notes = said(caplog, HARDWARE)
    assert len(notes) == 1 and notes[0].startswith(
        "drives 'j1', 'j2', 'j3': no 0x6007: on manager loss"), notes
