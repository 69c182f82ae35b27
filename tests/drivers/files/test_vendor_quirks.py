"""drivers/files/device_file.py, capabilities.py: more vendor-file quirks, each as its own small
variant of tests/fixtures/eds/minimal.eds written for the test: a file the project can run runs
(check-config, the simulator, the demo's walk-through with its torque-off), one it cannot is refused
in one line naming the file, the object and why.

    a default PDO mapping naming an object the file does not describe (a vendor object
    left out of the file): the simulator starts that PDO unmapped, the master remaps it
    a file without 0x6060, or with a read-only one: no mode can be set, refused at planning
    PDO mapping objects written with CompactSubObj: every entry counts, not sub-index 1
    names where numbers belong (ObjectType=VAR, DataType=UNSIGNED16, PDOMapping=TRUE), a
    missing ParameterName, header values that are no numbers, UTF-16 text: read
    a manufacturer object canopen cannot read: left out, noted; a standard one: refused
    naming its section and key
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest
from fixtures.driver_rig import INCREMENTS_PER_REV, RATED_TORQUE_NM
from fixtures.paths import TESTS

from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_plan import plan_drive

EDS = TESTS / "fixtures" / "eds"


def variant(tmp_path: Path, name: str, *edits: tuple[str, str], add: str = "") -> str:
    """minimal.eds with each (old, new) replaced once (old must be there) and ``add``
    appended."""
    text = (EDS / "minimal.eds").read_text()
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / name
    path.write_text(text + add)
    return str(path)


def drive(path: str, **kw) -> DriveConfig:
    kw.setdefault("modes", ("csp",))
    return DriveConfig("j1", 1, INCREMENTS_PER_REV, RATED_TORQUE_NM, eds=path, **kw)


def walk_through(path: str) -> list[str]:
    from rocoma_can.cli.demo.walkthrough import DemoOptions, Walkthrough
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=2.0, eds=path),
                         out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert report.steps[-1].name == "loop stop -> torque-off frames"
    return lines


def test_a_default_mapping_naming_an_undescribed_object_runs(tmp_path, sim_segment_factory,
                                                              caplog):
    """TPDO1's default mapping names 0x2001:0, a vendor object the file does not list: the
    simulated drive raised SdoAbortedError from its power-on (a traceback from `demo --eds`
    and `sim --eds`); it starts that PDO unmapped and says so, bring-up remaps it."""
    path = variant(tmp_path, "undescribed_default.eds",
                   ("DefaultValue=0x60610008", "DefaultValue=0x20010008"))
    with caplog.at_level(logging.WARNING, "rocoma_can.drivers.sim.segment"):
        segment = sim_segment_factory([1], eds_path=path)
    assert segment.drives[1].od_value(0x1A00, 0) == 0
    assert "default mapping of 0x1A00 (0x2001:0) names an object it does not describe" \
        in caplog.text
    plan_drive(drive(path))  # check-config: a writable mapping is the master's to set
    walk_through(path)


@pytest.mark.parametrize("edit, why", [
    ("drop", "has no 0x6060:0"),
    ("ro", "gives 0x6060:0 no write access")])
def test_a_file_where_no_mode_can_be_set_is_refused_in_one_line(tmp_path, edit, why, capsys):
    """Without a writable 0x6060 check-config said the mode is "set by SDO at start-up",
    and bring-up then failed on every drive (SDO abort 0x06020000)."""
    text = (EDS / "minimal.eds").read_text()
    edits = [(text[text.index("[6060]"):text.index("[6061]")], "")] if edit == "drop" else [(
        "[6060]\nParameterName=Modes of operation\nObjectType=0x7\nDataType=0x0002\n"
        "AccessType=rw", "[6060]\nParameterName=Modes of operation\nObjectType=0x7\n"
        "DataType=0x0002\nAccessType=ro")]
    edits.append(("DefaultValue=0x60600008", "DefaultValue=0x00000000"))
    path = variant(tmp_path, f"mode_{edit}.eds", *edits)
    expected = f"0x6060 (modes of operation): {path} {why}, so mode CSP cannot be set"
    with pytest.raises(ValueError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        plan_drive(drive(path))
    from rocoma_can.cli.main import main
    assert main(["demo", "--eds", path, "--no-record"]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and expected in out[0], out


def without(text: str, index: str) -> str:
    """``text`` without object ``index``: its section and its sub-sections."""
    kept = re.split(r"\n(?=\[)", text)
    return "\n".join(part for part in kept
                     if not part.startswith((f"[{index}]", f"[{index}sub")))


def _compact(text: str, index: str, entries: int, values: list[str] | None) -> str:
    """[index] written as CiA 306's compact array: its sub-sections gone, CompactSubObj=N,
    a DCF-style [indexValue] section with ``values``."""
    lines, out, skip = text.splitlines(), [], False
    for line in lines:
        if line.startswith("["):
            skip = line.startswith(f"[{index}sub")
            if line == f"[{index}]":
                out += [line, f"ParameterName=Mapping {index}", "ObjectType=0x8",
                        "DataType=0x0007", "AccessType=rw", "PDOMapping=0",
                        f"CompactSubObj={entries}", "DefaultValue=0", ""]
                skip = True
                continue
        if not skip:
            out.append(line)
    if values is not None:
        out += ["", f"[{index}Value]", f"NrOfEntries={len(values)}"]
        out += [f"{n}={v}" for n, v in enumerate(values, start=1)]
    return "\n".join(out) + "\n"


def test_a_compact_pdo_mapping_has_all_its_entries(tmp_path):
    """One RPDO and one TPDO, their mapping objects written with CompactSubObj=8: canopen
    keeps sub-index 1 only, so the drive read as "at most 1 objects each" and was refused
    ("RPDO needs more PDOs ... than the 1 it lets us map"). They have eight entries each."""
    from rocoma_can.drivers.files.capabilities import read_capabilities
    text = (EDS / "minimal.eds").read_text()
    for index in ("1401", "1402", "1403", "1601", "1602", "1603",
                  "1801", "1802", "1803", "1A01", "1A02", "1A03"):  # one PDO each way
        text = without(text, index)
    text = _compact(text, "1600", 8, ["0x60400010", "0x60600008", "0x607A0020"])
    text = _compact(text, "1A00", 8, None)
    path = tmp_path / "compact.eds"
    path.write_text(text)
    caps = read_capabilities(str(path), 1)
    (rpdo,), (tpdo,) = caps.rpdos, caps.tpdos
    assert (rpdo.max_objects, tpdo.max_objects) == (8, 8)
    assert rpdo.mapping == (0x60400010, 0x60600008, 0x607A0020) and rpdo.mapping_writable
    assert tpdo.mapping == () and tpdo.mapping_writable  # entries 0: nothing mapped yet
    plan = plan_drive(drive(str(path)))
    assert [p.names for p in plan.layout.rpdos] == [("controlword", "mode", "target_position")]
    walk_through(str(path))


CONTROLWORD = ("[6040]\nParameterName=Controlword\nObjectType=0x7\nDataType=0x0006\n"
               "AccessType=rw\nDefaultValue=0\nPDOMapping=1\n")
VENDOR_OBJECT = ("\n[2100]\nParameterName=Vendor tuning\nObjectType=0x7\nDataType={type}\n"
                 "AccessType=rw\nDefaultValue=0\n")


def test_names_where_numbers_belong_are_read_as_those_numbers(tmp_path):
    """Hand-written files spell ObjectType, DataType and PDOMapping by name; canopen read the
    file as "not a readable EDS/DCF file (ValueError: invalid literal for int() with base 0:
    'UNSIGNED16')", naming neither the object nor the key."""
    from rocoma_can.drivers.files.capabilities import read_capabilities
    path = variant(tmp_path, "named.eds", (CONTROLWORD, CONTROLWORD.replace(
        "ObjectType=0x7", "ObjectType=VAR").replace("DataType=0x0006", "DataType=Unsigned16")
        .replace("PDOMapping=1", "PDOMapping=TRUE").replace("ParameterName=Controlword\n", "")),
        ("VendorNumber=0x00000000", "VendorNumber=ACME"), ("Lines=0", "Lines=some"))
    caps = read_capabilities(path, 1)
    controlword = caps.object_dictionary[0x6040]
    assert (controlword.data_type, controlword.pdo_mappable, controlword.name) == \
        (0x0006, True, "0x6040")
    assert any("[DeviceInfo] VendorNumber=ACME" in note for note in caps.file_notes)
    plan_drive(drive(path))


@pytest.mark.parametrize("vendor_type", ["", "0x00ZZ", "FLOAT"])
def test_a_manufacturer_object_that_cannot_be_read_is_left_out(tmp_path, vendor_type):
    """A vendor object without a data type, or with one that is no data type, made the whole
    file unreadable, though rocoma-can commands no manufacturer object: it is left out, and
    the file's notes say which and why."""
    from rocoma_can.drivers.files.capabilities import read_capabilities
    path = variant(tmp_path, "vendor.eds",
                   add=VENDOR_OBJECT.format(type=vendor_type) + "\n[2101sub1]\n"
                   "ParameterName=orphan\nDataType=0x0007\nAccessType=rw\n")
    caps = read_capabilities(path, 1)
    assert 0x2100 not in caps.object_dictionary and 0x2101 not in caps.object_dictionary
    note = next(n for n in caps.file_notes if n.startswith("manufacturer objects"))
    assert "0x2100 ([2100] " in note and "0x2101 ([2101sub1] is a sub-index of [2101]" in note
    plan_drive(drive(path))


@pytest.mark.parametrize("edit, problem", [
    (("DataType=0x0006", "DataType=0x00ZZ"), "[6040] DataType=0x00ZZ is not a data type"),
    (("DataType=0x0006\n", ""), "[6040] has no DataType"),
    (("AccessType=rw\nDefaultValue=0\nPDOMapping=1", "DefaultValue=0\nPDOMapping=1"),
     "[6040] has no AccessType"),
    (("PDOMapping=1", "PDOMapping=maybe"), "[6040] PDOMapping=maybe is neither 0 nor 1"),
    (("ObjectType=0x7", "ObjectType=THING"), "[6040] ObjectType=THING is not an object type"),
])
def test_a_standard_object_that_cannot_be_read_refuses_the_file_naming_it(
        tmp_path, edit, problem, capsys):
    from rocoma_can.drivers.files.capabilities import CapabilityError, read_capabilities
    old, new = edit
    path = variant(tmp_path, "broken.eds", (CONTROLWORD, CONTROLWORD.replace(old, new)))
    with pytest.raises(CapabilityError) as refused:
        read_capabilities(path, 1)
    assert str(refused.value).startswith(f"{path}: {problem}")
    from rocoma_can.cli.main import main
    assert main(["demo", "--eds", path, "--no-record"]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and problem in out[0], out


def test_a_sub_index_without_its_object_refuses_the_file_naming_both(tmp_path):
    from rocoma_can.drivers.files.capabilities import CapabilityError, read_capabilities
    text = (EDS / "minimal.eds").read_text()
    head = text[text.index("[1600]\n"):text.index("[1600sub0]")]
    path = variant(tmp_path, "orphan.eds", (head, ""))
    with pytest.raises(CapabilityError, match=re.escape(
            "[1600sub0] is a sub-index of [1600], which the file does not have")):
        read_capabilities(path, 1)


def test_a_utf16_file_is_read(tmp_path):
    """Some Windows tools save UTF-16 with a byte-order mark: it was refused with a garbled
    line (its text read as Latin-1)."""
    from rocoma_can.drivers.files.capabilities import read_capabilities
    path = tmp_path / "utf16.eds"
    path.write_bytes((EDS / "minimal.eds").read_text().encode("utf-16"))
    caps = read_capabilities(str(path), 1)
    assert "UTF-16 text: read as such" in caps.file_notes
    plan_drive(drive(str(path)))


RESOLUTION = """
[608F]
ParameterName=Position encoder resolution
ObjectType=0x9
SubNumber=3

[608Fsub0]
ParameterName=Highest sub-index supported
DataType=0x0005
AccessType=const
DefaultValue=2

[608Fsub1]
ParameterName=Encoder increments
DataType=0x0007
AccessType=rw
DefaultValue=1

[608Fsub2]
ParameterName=Motor revolutions
DataType=0x0007
AccessType=rw
DefaultValue=10
"""


@pytest.mark.parametrize("edits, add, problem", [
    ((), RESOLUTION, "0x608F (position encoder resolution) is 1 increment(s) per 10 "
     "revolutions: less than one a revolution"),
    ((("DefaultValue=1000\nPDOMapping=0", "DefaultValue=-1\nPDOMapping=0"),), "",
     "0x6076 (rated torque) is -1"),
])
def test_the_demo_refuses_a_scaling_it_cannot_use_naming_the_object(tmp_path, edits, add,
                                                                     problem, capsys):
    """The demo fits its joints' scaling to the file: 1 increment per 10 revolutions said
    "increments_per_rev must be a positive integer, got 0", a rated torque of -1 "rated_torque_nm
    must be a positive number, got -0.001": neither named the file's object."""
    path = variant(tmp_path, "scaling.eds", *edits, add=add)
    from rocoma_can.cli.main import main
    assert main(["demo", "--eds", path, "--no-record"]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and problem in out[0], out
