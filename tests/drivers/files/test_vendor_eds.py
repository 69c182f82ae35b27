"""drivers/files/device_file.py, capabilities.py: drives described by vendor-like EDS/DCF files
(tests/fixtures/eds/, modelled on typical vendor files): what check-config reports, that the
simulator emulates exactly the file (its objects, access types and modes), bring-up, a cyclic
command, and e-stop -> torque-off frames on the drive's own PDO layout.

    fixed_pdo.eds        read-only mappings: RPDO1 = controlword + target position,
                         TPDO1 = statusword + position, TPDO2 = velocity + torque; CSP, PP
    no_abort_option.eds  no 0x6007; 0x1029 and node guarding instead
    commissioned.dcf     the DCF of node 5: ParameterValue over DefaultValue, $NODEID COB-IDs
    minimal.eds          no 0x6077, no 0x608F, no 0x6091; empty defaults
    arm_ip_pp_vl.eds     a robot-arm joint: PP, VL and IP only, no 0x6007 (modes elsewhere)
    hand_written.eds     every reading quirk: a Latin-1 byte, a key given twice, CRLF with
                         bare LFs, 0x1000 without value and 0x6502 empty, upper-case access,
                         lower-case hex, $NodeId, two's-complement hex, a [TypeDefinitions]
                         record type, a factor group with empty values
    node1_baked.dcf      a DCF exported for node 1 (DeviceCommissioning, COB-IDs 0x201...)
    tight_od.eds         0x6060 and 0x607A not PDO-mappable, one TPDO of two objects
    fixed_split.eds      fixed mappings split over slots: RPDO1 = controlword, RPDO2 =
                         controlword + target, TPDO3/TPDO4 = statusword + position/velocity
"""
from __future__ import annotations

import struct

import canopen
import pytest
from fixtures.driver_rig import INCREMENTS_PER_REV, RATED_TORQUE_NM, VIRTUAL, Rig
from fixtures.paths import EDS, ROOT

from rocoma_can.drivers.bringup.named_sdo import NamedSdo, ObjectRefused
from rocoma_can.drivers.files.capabilities import read_capabilities
from rocoma_can.drivers.files.device_file import read_device_file
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_plan import plan_drive
from rocoma_can.drivers.protocol import cia301, cia402


def drive(file: str, node_id: int = 1, **kw) -> DriveConfig:
    kw.setdefault("modes", ("csp",))
    return DriveConfig("j1", node_id, INCREMENTS_PER_REV, RATED_TORQUE_NM,
                       eds=str(EDS / file), **kw)


# --- what check-config says ------------------------------------------------------------------
def test_a_fixed_mapping_is_used_as_it_is():
    plan = plan_drive(drive("fixed_pdo.eds"))
    (rpdo,), tpdos = plan.layout.rpdos, plan.layout.tpdos
    assert rpdo.fixed and rpdo.names == ("controlword", "target_position")
    assert [p.names for p in tpdos] == [("statusword", "position"), ("velocity", "torque")]
    assert all(p.fixed for p in tpdos)
    report = "\n".join(plan.report())
    assert "fixed RPDO1 [controlword, target_position]" in report
    assert "RPDO1 fixed (<= 2 objects)" in report


def test_a_fixed_mapping_of_a_string_is_a_clear_error(tmp_path):
    """A fixed TPDO that maps a VISIBLE_STRING (0x1008, device name) raised KeyError from
    the struct table through check-config; it names the object now."""
    text = (EDS / "fixed_pdo.eds").read_text()
    text = text.replace("[MandatoryObjects]\nSupportedObjects=3\n1=0x1000\n2=0x1001\n3=0x1018",
                        "[MandatoryObjects]\nSupportedObjects=4\n1=0x1000\n2=0x1001\n"
                        "3=0x1018\n4=0x1008")
    text += ("\n[1008]\nParameterName=Manufacturer device name\nObjectType=0x7\n"
             "DataType=0x0009\nAccessType=const\nDefaultValue=A\nPDOMapping=1\n")
    text = text.replace("DefaultValue=0x60640020", "DefaultValue=0x10080008", 1)
    strings = tmp_path / "string_in_pdo.eds"
    strings.write_text(text)
    with pytest.raises(ValueError, match="maps 0x1008:0, which its file gives a type a PDO "
                                         "cannot carry as a number"):
        plan_drive(drive(str(strings)))


def test_a_fixed_mapping_says_what_it_cannot_carry(tmp_path):
    with pytest.raises(ValueError, match="CSV is not supported: its 0x6502 = 0x81 lists PP, CSP"):
        plan_drive(drive("fixed_pdo.eds", modes=("csv",)))
    csv_too = tmp_path / "fixed_csv.eds"  # lists CSV, but no fixed RPDO carries 0x60FF
    csv_too.write_text((EDS / "fixed_pdo.eds").read_text().replace(
        "DefaultValue=0x00000081", "DefaultValue=0x00000181"))
    config = DriveConfig("j1", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM, eds=str(csv_too),
                         modes=("csv",))
    with pytest.raises(ValueError, match=r"mode CSV needs its target 0x60FF:0 in an RPDO, "
                                         r"but its file has no 0x60FF:0; modes it can run: "
                                         r"PP, CSP"):
        plan_drive(config)
    with pytest.raises(ValueError, match="0x6060 .*none carries 0x6060:0.* configure one mode"):
        plan_drive(DriveConfig("j1", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM, eds=str(csv_too),
                               modes=("csp", "csv")))


def test_no_abort_option_is_said_and_the_other_ways_are_named():
    plan = plan_drive(drive("no_abort_option.eds"))
    report = "\n".join(plan.report())
    assert "missing: 0x6007" in report
    assert "heartbeat consumer 0x1016 -> EMCY 0x8130 only" in report
    assert "0x1029:1 communication error" in report
    # it has a heartbeat: node guarding is not driven
    assert "life guarding 0x100C/0x100D" not in report
    assert any("no 0x6007" in n for n in plan.notes)


def test_a_drive_that_ignores_losing_the_manager_needs_an_explicit_yes(tmp_path):
    text = (EDS / "no_abort_option.eds").read_text()
    unsupervised = tmp_path / "unsupervised.eds"  # and no heartbeat consumer either
    unsupervised.write_text(text.replace("[1016sub1]\nParameterName=Consumer heartbeat time 1"
                                         "\nObjectType=0x7\nDataType=0x0007\nAccessType=rw",
                                         "[1016sub1]\nParameterName=Consumer heartbeat time 1"
                                         "\nObjectType=0x7\nDataType=0x0007\nAccessType=ro"))
    assert not read_capabilities(str(unsupervised), 1).heartbeat_consumer
    config = DriveConfig("j1", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM, eds=str(unsupervised))
    # node guarding is then how it watches the manager (0x1029 behind it) ...
    assert plan_drive(config).guarded
    # ... and without it, nothing does
    unsupervised.write_text(unsupervised.read_text().replace(
        "ParameterName=Life time factor\nObjectType=0x7\nDataType=0x0005\nAccessType=rw",
        "ParameterName=Life time factor\nObjectType=0x7\nDataType=0x0005\nAccessType=ro"))
    with pytest.raises(ValueError, match="losing the manager would leave this drive running.*"
                                         "accept_unsupervised: true"):
        plan_drive(config)
    accepted = plan_drive(DriveConfig("j1", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM,
                                      eds=str(unsupervised), accept_unsupervised=True))
    assert any(n.startswith("RISK accepted") for n in accepted.notes)


def test_a_dcf_gives_its_commissioned_values_and_its_node():
    caps = read_capabilities(str(EDS / "commissioned.dcf"), 5)
    assert caps.commissioned_node_id == 5
    assert caps.value(cia301.PRODUCER_HEARTBEAT_TIME) == 50  # ParameterValue, not 100
    assert caps.value(cia402.POSITION_ENCODER_RESOLUTION, 1) == 0x40000
    assert caps.rpdos[0].cob_id == 0x205 and caps.tpdos[0].cob_id == 0x185  # $NODEID
    assert caps.mode_names == ["CSP", "CSV", "CST"]
    # the same DCF for another node: its values, that node's COB-IDs, said in a note
    other = plan_drive(drive("commissioned.dcf", node_id=3))
    assert "a DCF commissioned for node 5, used for node 3: its values are taken, its " \
        "node's COB-IDs are not" in other.notes
    assert other.caps.value(cia301.PRODUCER_HEARTBEAT_TIME) == 50
    assert {p.cob_id for p in other.layout.rpdos} == {0x203}
    assert {p.cob_id for p in other.layout.tpdos} <= {0x183, 0x283}


def test_missing_feedback_objects_turn_that_feedback_off_and_say_so():
    plan = plan_drive(drive("minimal.eds"))
    assert plan.drive.feedback == ("position", "velocity")
    assert not plan.layout.maps("torque")
    assert any("no 0x6077: torque feedback off" in n for n in plan.notes)
    assert any("no 0x608F: increments_per_rev comes from the config alone" in n
               for n in plan.notes)
    with pytest.raises(ValueError, match="feedback 'torque': the drive has no 0x6077"):
        plan_drive(drive("minimal.eds", feedback=("position", "torque")))


def test_a_mode_the_drive_does_not_list_is_refused_naming_both():
    with pytest.raises(ValueError, match=r"mode CSP is not supported: its 0x6502 = 0x43 "
                                         r"lists PP, VL, IP"):
        plan_drive(drive("arm_ip_pp_vl.eds"))


# --- the layout's limits, from the review of real files ---------------------------------------
def _variant(tmp_path, name: str, edit) -> str:
    text = (ROOT / "eds" / "cia402_drive.eds").read_text()
    path = tmp_path / name
    path.write_text(edit(text))
    return str(path)


def test_each_mapping_object_takes_at_most_its_own_entries(tmp_path):
    """RPDO1's mapping object has two entries: controlword + mode fill it, the target goes
    to RPDO2 (first fit per slot, not the smallest slot's limit for all)."""
    def two_entries(text: str) -> str:
        for sub in range(3, 9):
            text = text.replace(f"[1600sub{sub}]\n", f"[X1600sub{sub}]\n")
        return text.replace("[1600]\nParameterName=RPDO1 mapping parameter\n"
                            "ObjectType=0x9\nSubNumber=9",
                            "[1600]\nParameterName=RPDO1 mapping parameter\n"
                            "ObjectType=0x9\nSubNumber=3").replace(
            "[1600sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
            "DataType=0x0005\nAccessType=rw\nDefaultValue=3",
            "[1600sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
            "DataType=0x0005\nAccessType=rw\nDefaultValue=2")
    path = _variant(tmp_path, "two.eds", two_entries)
    caps = read_capabilities(path, 1)
    assert caps.rpdos[0].max_objects == 2
    plan = plan_drive(drive_with(path))
    assert [p.names for p in plan.layout.rpdos] == [("controlword", "mode"),
                                                    ("target_position",)]


def drive_with(path: str, **kw) -> DriveConfig:
    kw.setdefault("modes", ("csp",))
    return DriveConfig("j1", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM, eds=path, **kw)


def test_a_fixed_rpdo_never_sends_a_target_it_is_not_told(tmp_path):
    """A fixed RPDO1 = controlword + target position + target velocity on a CSP drive: the
    velocity target is a constant (the file's 0), not a live value; a non-zero one is
    refused."""
    fixed = (EDS / "fixed_pdo.eds").read_text().replace(
        "[1600sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\nDataType=0x0005"
        "\nAccessType=const\nDefaultValue=2",
        "[1600sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\nDataType=0x0005"
        "\nAccessType=const\nDefaultValue=3")
    assert "DefaultValue=3" in fixed
    # a third entry, 0x6072 max torque (16 bit), left at its file value 3000: not a target
    fixed = fixed.replace("[1600sub2]", "[1600sub3]\nParameterName=Mapped object 3\n"
                          "ObjectType=0x7\nDataType=0x0007\nAccessType=const\n"
                          "DefaultValue=0x60720010\nPDOMapping=0\n\n[1600sub2]")
    fixed = fixed.replace("[1600]\nParameterName=RPDO1 mapping parameter\nObjectType=0x9\n"
                          "SubNumber=3", "[1600]\nParameterName=RPDO1 mapping parameter\n"
                          "ObjectType=0x9\nSubNumber=4")
    path = tmp_path / "fixed3.eds"
    path.write_text(fixed)
    plan = plan_drive(drive_with(str(path)))
    (rpdo,) = plan.layout.rpdos
    assert [(e.name, e.constant) for e in rpdo.entries] == [
        ("controlword", None), ("target_position", None), ("0x6072:0", 3000)]
    assert "0x6072:0 = 3000" in "\n".join(plan.report())
    refused = tmp_path / "fixed4.eds"  # the third entry a velocity target the file sets
    refused.write_text(fixed.replace("DefaultValue=0x60720010", "DefaultValue=0x60FF0020")
                       + "\n[60FF]\nParameterName=Target velocity\nObjectType=0x7\n"
                       "DataType=0x0004\nAccessType=rw\nDefaultValue=100\nPDOMapping=1\n")
    with pytest.raises(ValueError, match=r"maps 0x60FF:0, which rocoma-can does not command "
                                         r"here and would send as the file's value 100"):
        plan_drive(drive_with(str(refused)))


def test_unused_channels_are_switched_off_and_0x1029_set_at_bring_up(tmp_path,
                                                                    sim_segment_factory,
                                                                    bus_factory):
    """The generic drive's RPDO3/4 and TPDO3/4 are not needed for CSP: invalid after bring-up;
    a 0x1029:1 of "no state change" becomes "pre-operational"."""
    path = _variant(tmp_path, "no_change.eds", lambda text: text.replace(
        "[1029sub1]\nParameterName=Communication error\nObjectType=0x7\n"
        "DataType=0x0005\nAccessType=rw\nDefaultValue=0",
        "[1029sub1]\nParameterName=Communication error\nObjectType=0x7\n"
        "DataType=0x0005\nAccessType=rw\nDefaultValue=1"))
    segment = sim_segment_factory([1], eds_path=path)
    assert segment.drives[1].od_value(cia301.ERROR_BEHAVIOR, 1) == 1
    r = Rig.for_setup(bus_factory(), [1], VIRTUAL, modes=("csp",), drive={"eds": path})
    try:
        assert r.run_until(lambda: not r.hw.starting, VIRTUAL.bring_up_budget(1))
        sim = segment.drives[1]
        assert sim.od_value(cia301.ERROR_BEHAVIOR, 1) == 0
        for comm in (0x1402, 0x1403, 0x1802, 0x1803):
            assert sim.od_value(comm, 1) & 0x8000_0000, hex(comm)
        assert not sim.od_value(0x1400, 1) & 0x8000_0000
    finally:
        r.close()


# --- files as vendors write them --------------------------------------------------------------
def test_a_hand_written_file_is_read_as_its_vendor_meant_it():
    device = read_device_file(str(EDS / "hand_written.eds"))
    assert device.notes[0] == "not UTF-8 (byte 0x94 on line 49): read as Latin-1"
    assert "'1' in [ManufacturerObjects] (line 117)" in device.notes[1]
    assert "custom record types (0x40, [TypeDefinitions]) read as domains" in device.notes[2]
    assert {(0x1000, 0), (cia402.SUPPORTED_DRIVE_MODES, 0), (cia402.GEAR_RATIO, 1),
            (cia402.GEAR_RATIO, 2)} <= device.unknown
    od = device.object_dictionary(7)
    assert od[0x2000].default == -2  # 0xFFFE of an INTEGER16
    assert od[0x2001].data_type == canopen.objectdictionary.DOMAIN
    assert od[cia301.PRODUCER_HEARTBEAT_TIME].default == 200  # 0x00c8
    assert od[0x1800][1].default == 0x40000187  # $NodeId
    assert od[0x1000].access_type == "ro" and od[0x1000].default is None  # unknown, not 0


def test_check_config_says_what_is_read_from_the_drive():
    plan = plan_drive(drive("hand_written.eds"))
    lines = plan.report()
    assert "  modes: PP, PV, TQ, CSP, CSV, CST (from its target objects; 0x6502 read from " \
        "the drive)" in lines
    assert "  read from the drive at start-up (no value in the file): 0x1000 (device type), " \
        "0x6502 (supported modes), 0x6091 (gear ratio)" in lines
    assert any(n.startswith("not UTF-8 (byte 0x94") for n in plan.notes)
    with pytest.raises(ValueError, match=r"mode IP is not supported: its target objects "
                                         r"\(0x6502 has no value in the file\) lists PP, PV"):
        plan_drive(drive("hand_written.eds", modes=("ip",)))


def test_a_dcf_exported_for_node_1_gives_each_node_its_own_cob_ids():
    caps = read_capabilities(str(EDS / "node1_baked.dcf"), 3)
    assert caps.commissioned_node_id == 1  # [DeviceCommissioning], as some tools spell it
    assert caps.rpdos[0].cob_id == 0x203 and caps.tpdos[0].cob_id == 0x40000183
    assert caps.rpdos[1].cob_id == 0x80000303  # its flag bits kept
    assert caps.file_notes[0].startswith("COB-IDs the file gives for node 1 re-derived for "
                                         "node 3: 0x1014:0 0x81, 0x1400:1 0x201")
    at_home = read_capabilities(str(EDS / "node1_baked.dcf"), 1)
    assert at_home.rpdos[0].cob_id == 0x201 and not at_home.file_notes


def test_a_tight_dictionary_runs_what_it_can_and_says_what_it_cannot():
    plan = plan_drive(drive("tight_od.eds", modes=("ip",)))
    assert plan.layout.rpdos[0].names == ("controlword", "target_position")  # no 0x6060
    assert "no RPDO can carry 0x6060: mode IP is set by SDO at start-up, before enabling" \
        in plan.notes
    assert plan.drive.feedback == ("position",)
    assert "its TPDOs carry statusword and position only: velocity, torque feedback left " \
        "out (JointState stays 0 there)" in plan.notes
    assert "  modes ruled out: PP (0x607A not PDO-mappable)" in plan.report()
    with pytest.raises(ValueError, match=r"mode PP needs its target 0x607A:0 in an RPDO, but "
                                         r"its file does not let a PDO carry 0x607A:0 "
                                         r"\(PDOMapping=0\); modes it can run: IP"):
        plan_drive(drive("tight_od.eds", modes=("pp",)))
    with pytest.raises(ValueError, match=r"TPDO needs more PDOs for statusword, position, "
                                         r"velocity than the 1 it lets us map"):
        plan_drive(drive("tight_od.eds", modes=("ip",), feedback=("position", "velocity")))


def test_fixed_mappings_are_used_only_where_they_add_something():
    plan = plan_drive(drive("fixed_split.eds"))
    assert [(p.number, p.names) for p in plan.layout.rpdos] == [
        (2, ("controlword", "target_position"))]  # RPDO1 (controlword alone) adds nothing
    assert [(p.number, p.names) for p in plan.layout.tpdos] == [
        (3, ("statusword", "position")), (4, ("statusword", "velocity"))]


def test_bring_up_names_the_object_the_drive_refused(sim_bench):
    bench = sim_bench(1, eds_path=str(EDS / "minimal.eds"))
    sdo = NamedSdo(bench.node(1).sdo)
    with pytest.raises(ObjectRefused) as info:
        sdo.download(0x1000, 0, struct.pack("<I", 1))
    assert str(info.value).startswith("SDO write of 0x1000:0 = 0x1 refused: Code 0x06010002")


def test_a_mapping_count_beyond_its_entries_is_refused_alike_everywhere(tmp_path):
    """0x1600:0 says 200 objects, the file gives 8: the same line from check-config, the
    master and the simulator, never the simulator's SDO traceback."""
    bad = tmp_path / "count_200.eds"
    bad.write_text((EDS / "minimal.eds").read_text().replace(
        "[1600sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
        "DataType=0x0005\nAccessType=rw\nDefaultValue=3",
        "[1600sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
        "DataType=0x0005\nAccessType=rw\nDefaultValue=200"))
    assert "DefaultValue=200" in bad.read_text()
    why = f"{bad}: 0x1600:0 says 200 mapped objects but the file gives 8 (0x1600:1..8)"
    with pytest.raises(ValueError) as planned:
        plan_drive(drive(str(bad)))
    assert str(planned.value) == f"drive 'j1': {why}"
    from rocoma_can.drivers.sim.objects import load_object_dictionary
    with pytest.raises(ValueError) as simulated:
        load_object_dictionary(str(bad), 1)
    assert str(simulated.value) == f"simulated drive 1: {why}"
