"""drivers/files/identity.py: a drive's ``identity:`` in the config, what check-config says bring-up
will require of each drive's 0x1018, and how a found identity is judged (no bus: the bring-up side
is tests/drivers/bringup/test_driver_bus_identity.py)."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from fixtures.configs import good
from fixtures.paths import ROOT, TESTS

from rocoma_can.cli.main import main
from rocoma_can.drivers.files.capabilities import read_capabilities
from rocoma_can.drivers.files.identity import Identity, IdentityCheck
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.plan.drive_plan import plan_drives
from rocoma_can.runtime.config import ConfigError, validate

EDS = TESTS / "fixtures" / "eds"


def vendor_file(tmp_path: Path, vendor: str = "0x0000009A", product: str = "0x00001234",
                name: str = "vendor.eds") -> Path:
    """The generic drive's EDS with [DeviceInfo] naming a vendor and product."""
    text = (ROOT / "eds" / "cia402_drive.eds").read_text()
    text = text.replace("VendorNumber=0x00000000", f"VendorNumber={vendor}")
    text = text.replace("ProductNumber=0x00000402", f"ProductNumber={product}")
    path = tmp_path / name
    path.write_text(text)
    return path


def check(configured, od_file: Path | None = None) -> IdentityCheck:
    caps = read_capabilities(str(od_file) if od_file else None, 1)
    return IdentityCheck.of(configured, caps.object_dictionary, caps.source)


# --- the config key --------------------------------------------------------------------------
def test_identity_takes_any_subset_hex_as_yaml_reads_it_or_any():
    drive = yaml.safe_load("name: knee\nnode_id: 2\nincrements_per_rev: 4096\n"
                           "rated_torque_nm: 1.0\nidentity: {serial: 0x00001234, revision: 7}")
    assert DriveConfig.from_dict(drive).identity == Identity(revision=7, serial=0x1234)
    assert DriveConfig("knee", 2, 4096, 1.0, identity="any").identity == "any"
    assert DriveConfig("knee", 2, 4096, 1.0).identity is None


@pytest.mark.parametrize("given, said", [
    ({"serial": "0x1234"}, "identity.serial must be an unsigned 32-bit integer "
                           "(0..0xFFFFFFFF) (write a hex number unquoted: 0x1234), got '0x1234'"),
    ({"serial": -1}, "identity.serial must be an unsigned 32-bit integer (0..0xFFFFFFFF), "
                     "got -1"),
    ({"vendor_id": 1 << 32}, "identity.vendor_id must be an unsigned 32-bit integer "
                             "(0..0xFFFFFFFF), got 4294967296"),
    ({"product_code": True}, "identity.product_code must be an unsigned 32-bit integer "
                             "(0..0xFFFFFFFF), got True"),
    ({"serial_number": 5}, "identity.serial_number: unknown key (known: vendor_id, "
                           "product_code, revision, serial)"),
    ("all", "identity must be 'any' (not checked) or a mapping of one or more of vendor_id, "
            "product_code, revision, serial, got 'all'"),
    ({}, "identity must be 'any' (not checked) or a mapping of one or more of vendor_id, "
         "product_code, revision, serial, got {}"),
], ids=["quoted hex", "negative", "33 bits", "bool", "unknown key", "a word", "empty"])
def test_a_bad_identity_is_one_line_naming_the_drive_and_key(given, said):
    cfg = good()
    cfg["drives"][1]["identity"] = given
    with pytest.raises(ConfigError) as caught:
        validate(cfg)
    assert caught.value.problems == [f"<memory>: drives[1]: drive 'j2': {said}"]


def test_the_axes_of_a_node_say_its_identity_alike():
    two = str(EDS / "two_axes.eds")
    cfg = good()
    cfg["drives"] = [{"name": f"a{n}", "node_id": 1, "axis": n, "increments_per_rev": 4096,
                      "rated_torque_nm": 1.0, "eds": two, "modes": ["csp", "csv"]}
                     for n in (1, 2)]
    cfg["drives"][0]["identity"] = {"serial": 5}
    with pytest.raises(ConfigError, match=r"drives: drive 'a2': node 1 is also drive 'a1' "
                                          r"\(axis 1\), whose identity is .*one node has one "
                                          r"identity"):
        validate(cfg)


# --- what bring-up will require ------------------------------------------------------------
def test_what_is_required_and_where_it_comes_from(tmp_path):
    vendor = vendor_file(tmp_path)
    assert check(None).describe() == "identity: not checked: its file names no vendor"
    assert check(None, vendor).describe() == (
        "identity: vendor/product from its file (vendor_id 0x0000009A, product_code "
        "0x00001234)")
    assert check(Identity(serial=0x1234)).describe() == \
        "identity: serial 0x00001234 required"
    # the config's fields, and the file's vendor/product for what the config leaves
    assert check(Identity(product_code=0x99, serial=0x1234), vendor).describe() == (
        "identity: product_code 0x00000099, serial 0x00001234 required; vendor/product from "
        "its file (vendor_id 0x0000009A)")
    assert check("any", vendor).describe() == "identity: any (not checked)"
    assert check("any", vendor).wanted == () and check(None).wanted == ()
    # a product number without a vendor does not constrain (product codes are per vendor)
    assert check(None, vendor_file(tmp_path, vendor="0", name="novendor.eds")).wanted == ()


def test_the_file_identity_falls_back_to_its_0x1018_values(tmp_path):
    text = (ROOT / "eds" / "cia402_drive.eds").read_text()
    text = text.replace("VendorNumber=0x00000000\n", "")
    path = tmp_path / "no_deviceinfo_vendor.eds"
    # the generic file's 0x1018:1 default is 0 as well: give it one
    path.write_text(text.replace("ParameterName=Vendor-ID\nObjectType=0x7\nDataType=0x0007\n"
                                 "AccessType=ro\nDefaultValue=0x00000000",
                                 "ParameterName=Vendor-ID\nObjectType=0x7\nDataType=0x0007\n"
                                 "AccessType=ro\nDefaultValue=0x0000002A"))
    assert check(None, path).from_file == Identity(vendor_id=0x2A, product_code=0x402)


def test_a_found_identity_is_judged_naming_both_values(tmp_path):
    required = check(Identity(serial=0x1234, revision=3), vendor_file(tmp_path))
    assert required.wanted == ("vendor_id", "product_code", "revision", "serial")
    assert required.problem(Identity(0x9A, 0x1234, 3, 0x1234)) is None
    assert required.problem(Identity(0x9A, 0x1234, 3, 0x5678)) == \
        "serial 0x00001234 expected, 0x00005678 found: another drive of the same model " \
        "(replaced?)"
    # a subindex the device lacks: compared where the config asks for it, said so
    assert required.problem(Identity(0x9A, None, None, 0x1234)) == (
        "revision 0x00000003 expected, the drive has no 0x1018:3: not the drive the config "
        "names")
    assert required.problem(Identity(0x9B, 0x1234, 3, 0x1234)) == (
        "vendor_id 0x0000009B, product_code 0x00001234 found, its file vendor.eds is for "
        "vendor_id 0x0000009A, product_code 0x00001234: wrong file or wrong drive?")


def test_a_swap_is_suggested_only_when_the_device_is_another_configured_drive(tmp_path):
    """"swapped node ids or cables?" when the device found is one the config names for
    another drive; a device of another model, or one no drive of the config is, is not
    called a swap (a whole robot of wrong models said so for every drive)."""
    vendor = vendor_file(tmp_path)
    knee = check(Identity(serial=1), vendor)
    hip = ("drive 'hip' (node 2)", check(Identity(serial=2), vendor))
    assert knee.problem(Identity(0x9A, 0x1234, None, 2), [hip]) == (
        "serial 0x00000001 expected, 0x00000002 found: it is drive 'hip' (node 2): swapped "
        "node ids or cables?")
    assert knee.problem(Identity(0x9A, 0x1234, None, 7), [hip]) == (
        "serial 0x00000001 expected, 0x00000007 found: another drive of the same model "
        "(replaced?)")
    model = check(Identity(vendor_id=0x9A, product_code=0x1234), vendor)
    other_model = ("drive 'hip' (node 2)", check(Identity(vendor_id=0x9A,
                                                          product_code=0x1234), vendor))
    assert model.problem(Identity(0x9A, 0x99), [other_model]) == (
        "product_code 0x00001234 expected, 0x00000099 found: not the drive the config names")


# --- check-config -------------------------------------------------------------------------
def test_check_config_says_per_drive_what_identity_bring_up_requires(tmp_path, capsys):
    cfg = good()
    vendor = vendor_file(tmp_path)
    cfg["drives"] = [
        {"name": "knee", "node_id": 1, "identity": {"serial": 0x1234}},
        {"name": "hip", "node_id": 2, "eds": str(vendor)},
        {"name": "ankle", "node_id": 3, "eds": str(vendor), "identity": "any"},
        {"name": "toe", "node_id": 4}]
    for d in cfg["drives"]:
        d.update(increments_per_rev=4096, rated_torque_nm=1.0)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line for line in out if "identity" in line] == [
        "drive 'knee': identity: serial 0x00001234 required",
        "drive 'hip': identity: vendor/product from its file (vendor_id 0x0000009A, "
        "product_code 0x00001234)",
        "drive 'ankle': identity: any (not checked)",
        "drive 'toe': identity: not checked: its file names no vendor"]
    assert main(["check-config", "--drives", str(path)]) == 0
    assert "  identity: serial 0x00001234 required" in capsys.readouterr().out.splitlines()


def test_the_report_of_a_higher_axis_says_its_node_is_checked_by_the_lowest():
    two = str(EDS / "two_axes.eds")
    plans = plan_drives([DriveConfig(f"a{n}", 1, 4096, 1.0, eds=two, axis=n,
                                     modes=("csp", "csv"), identity={"serial": 5})
                         for n in (1, 2)])
    assert "  identity: serial 0x00000005 required" in plans[0].report()
    assert ("  identity: serial 0x00000005 required (the node's: checked by its lowest axis)"
            in plans[1].report())
