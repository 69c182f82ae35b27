"""rocoma_can/cli/init_config.py: `rocoma-can init-config`: a config from a scan of simulated drives
and a folder of device files, through the real CLI: each node matched to its file by vendor and
product, the identity it was seen with carried into the config, the rest as comments; the output
passes check-config and runs.

The tests taking ``sim_interface`` run on python-can's virtual bus and again on SocketCAN
vcan0 (the vcan suite, through tools/vcan-run)."""
from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import pytest
import yaml
from fixtures.budgets import GUEST_STALL, STALL
from fixtures.bus import scan_bus_args
from fixtures.init_config import bring_up
from fixtures.paths import TESTS

from rocoma_can.cli.main import main
from rocoma_can.drivers.files.identity import Identity

EDS = TESTS / "fixtures" / "eds"
VENDOR_A = EDS / "vendor_a.eds"  # vendor 0xAA, product 0x1234 in its [DeviceInfo]
STRANGER = Identity(vendor_id=0xBB, product_code=0x1)


def _folder(tmp_path: Path) -> Path:
    """The drives' files as a person keeps them: the vendor's, and one that is for no
    vendor (the generic CiA 402 file: made for no drive of a vendor, offered to those no
    file is made for)."""
    folder = tmp_path / "eds"
    folder.mkdir()
    shutil.copy(VENDOR_A, folder)
    shutil.copy(EDS.parent.parent.parent / "eds" / "cia402_drive.eds", folder)
    (folder / "notes.txt").write_text("not a device file")
    return folder


def _init_config(tmp_path: Path, interface: str, channel: str) -> tuple[Path, str]:
    out = tmp_path / "robot.yaml"
    stall = GUEST_STALL if interface == "socketcan" else STALL
    assert main(["init-config", *scan_bus_args(interface, channel, stall),
                 "--eds-dir", str(_folder(tmp_path)), "-o", str(out)]) == 0
    return out, out.read_text()


def test_each_matched_drive_carries_its_file_and_identity_the_rest_are_comments(
        sim_segment_factory, sim_interface, virtual_channel, tmp_path, capsys):
    channel = virtual_channel if sim_interface == "virtual" else "vcan0"
    sim_segment_factory([1, 2, 3], interface=sim_interface, eds_path=str(VENDOR_A),
                        identities={3: STRANGER})
    out, text = _init_config(tmp_path, sim_interface, channel)
    config = yaml.safe_load(text)
    drives = config["drives"]
    assert [(d["node_id"], d["eds"]) for d in drives] == [(1, "eds/vendor_a.eds"),
                                                          (2, "eds/vendor_a.eds")]
    assert [d["identity"] for d in drives] == [
        {"vendor_id": 0xAA, "product_code": 0x1234, "revision": 0, "serial": n}
        for n in (1, 2)]  # the revision its 0x1018:3 answers (the file's default)
    assert "# node 3: vendor_id 0x000000BB, product_code 0x00000001" in text
    assert "no file in" in text and "names this device; may fit: cia402_drive.eds (it " \
        "names no vendor" in text and "pick one with --eds 3=" in text
    assert "increments_per_rev not in its file: a guess" in text  # no 0x608F in the file
    assert config["bus"] == {"interface": sim_interface, "channel": channel,
                             "bitrate": 1_000_000}
    assert config["manager"]["node_id"] not in (1, 2, 3)
    assert config["manager"]["estop_must_be_cleared"] is True
    capsys.readouterr()
    assert main(["check-config", str(out)]) == 0, capsys.readouterr()




def test_the_generated_config_runs(sim_segment_factory, virtual_channel, tmp_path):
    """What init-config writes is a config the runtime brings up as it is (the identities
    it carries are the drives' own)."""
    sim_segment_factory([1, 2], eds_path=str(VENDOR_A))
    out, _ = _init_config(tmp_path, "virtual", virtual_channel)
    status = bring_up(out)
    assert [(s.node_id, s.phase) for s in status] == [(1, "READY"), (2, "READY")], status


def test_a_swapped_drive_is_refused_by_the_config_init_config_wrote(
        sim_segment_factory, virtual_channel, tmp_path):
    """The config remembers which drive was at which node id: against a bus where nodes 1
    and 2 swapped their drives, bring-up refuses both and says why."""
    segment = sim_segment_factory([1, 2], eds_path=str(VENDOR_A))
    out, _ = _init_config(tmp_path, "virtual", virtual_channel)
    segment.drives[1].swap(Identity(serial=2))
    segment.drives[2].swap(Identity(serial=1))
    status = bring_up(out)
    assert [s.phase for s in status] == ["FAILED", "FAILED"], status
    assert "serial 0x00000001 expected, 0x00000002 found: it is drive 'node2' (node 2): " \
        "swapped node ids or cables?" \
        in str(status[0].fault), status


def test_no_drive_to_configure_and_usage_errors(sim_segment_factory, virtual_channel,
                                                 tmp_path, capsys):
    sim_segment_factory([4], eds_path=str(VENDOR_A), identities={4: STRANGER})
    args = [*scan_bus_args("virtual", virtual_channel, STALL), "--eds-dir",
            str(_folder(tmp_path))]
    assert main(["init-config", *args]) == 1  # found a node, but no file for it
    err = capsys.readouterr().err
    assert "no drive could be configured" in err and "vendor_id 0x000000BB" in err
    assert main(["init-config", *args[:-1], str(tmp_path / "missing")]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert main(["init-config", "--channel", virtual_channel]) == 2  # no --eds-dir, no --eds


@pytest.mark.parametrize("output", ["missing/robot.yaml", "."])
def test_an_output_that_cannot_be_written_is_refused_before_the_scan(
        virtual_channel, tmp_path, capsys, output):
    """-o in a folder that does not exist, or naming a folder: one line, exit 2, and no scan
    (which takes seconds) before it."""
    started = time.monotonic()
    assert main(["init-config", "--interface", "virtual", "--channel", virtual_channel,
                 "--eds-dir", str(_folder(tmp_path)), "-o", str(tmp_path / output)]) == 2
    assert time.monotonic() - started < 1.0  # the scan alone takes longer
    err = capsys.readouterr().err.strip()
    assert err.startswith("rocoma-can: init-config: -o ") and "\n" not in err, err
    assert "Traceback" not in err


def test_files_it_cannot_read_are_said_also_when_no_drive_matched(
        sim_segment_factory, virtual_channel, tmp_path, capsys):
    """A folder of files that are not device files (and a symbolic link in a loop): each is
    named with why, also when nothing could be configured, where they explain why no file
    was for the drive."""
    sim_segment_factory([1], eds_path=str(VENDOR_A))
    folder = tmp_path / "eds"
    folder.mkdir()
    (folder / "drive.eds").write_text("not an EDS\n")
    (folder / "loop.eds").symlink_to("loop.eds")
    assert main(["init-config", *scan_bus_args("virtual", virtual_channel, STALL),
                 "--eds-dir", str(folder)]) == 1
    err = capsys.readouterr().err
    assert "note: drive.eds: not read" in err and "note: loop.eds: not read" in err, err
    assert "no drive could be configured" in err and "Traceback" not in err


# -- one matching rule, shared with bring-up; files that name too little are offered --------

VENDOR_ONLY = EDS / "vendor_only.eds"  # vendor 0xCC, no ProductNumber, no 0x1018:2 value
FAMILY = Identity(product_code=0x101)  # what a drive of that family says it is
PROJECT_EDS = EDS.parent.parent.parent / "eds"  # the checkout's own eds/


def _only(tmp_path: Path, *files: Path) -> Path:
    folder = tmp_path / "eds"
    folder.mkdir(exist_ok=True)
    for f in files:
        shutil.copy(f, folder)
    return folder


def _run(tmp_path: Path, channel: str, folder: Path | None, *extra: str,
         out: str | None = "robot.yaml") -> int:
    args = ["init-config", *scan_bus_args("virtual", channel, STALL), *extra]
    if folder is not None:
        args += ["--eds-dir", str(folder)]
    if out is not None:
        args += ["-o", str(tmp_path / out)]
    return main(args)


def test_a_file_that_names_no_product_is_offered_with_the_reason_and_picked_by_eds(
        sim_segment_factory, virtual_channel, tmp_path, capsys):
    """A vendor's one file for a family of drives (its [DeviceInfo] names the vendor, no
    ProductNumber): bring-up takes it for any drive of that vendor, init-config matched it
    to none and said "add its EDS/DCF" although it was in the folder. It is offered with
    the reason and the option that picks it; picked, it makes a config check-config
    accepts."""
    sim_segment_factory([1, 2], eds_path=str(VENDOR_ONLY), identities={1: FAMILY, 2: FAMILY})
    folder = _only(tmp_path, VENDOR_ONLY)
    assert _run(tmp_path, virtual_channel, folder) == 1
    err = capsys.readouterr().err
    assert "add its EDS/DCF" not in err, err
    assert (f"no file in {folder} names this device; may fit: vendor_only.eds (it names "
            "vendor 0x000000CC and no product number: any product of that vendor fits it): "
            f"pick one with --eds 1={folder}/vendor_only.eds") in err, err
    assert _run(tmp_path, virtual_channel, folder, "--eds", f"1={folder}/vendor_only.eds",
                "--eds", f"2={folder}/vendor_only.eds") == 0, capsys.readouterr()
    config = yaml.safe_load((tmp_path / "robot.yaml").read_text())
    assert [(d["node_id"], d["eds"], d["identity"]["product_code"]) for d in config["drives"]] \
        == [(1, "eds/vendor_only.eds", 0x101), (2, "eds/vendor_only.eds", 0x101)]
    text = (tmp_path / "robot.yaml").read_text()
    assert "# node 1: vendor_only.eds (picked by --eds; it names vendor 0x000000CC and no " \
           "product number" in text
    capsys.readouterr()
    assert main(["check-config", str(tmp_path / "robot.yaml")]) == 0, capsys.readouterr()


def test_a_file_that_names_no_vendor_is_offered_not_asked_for(sim_segment_factory,
                                                             virtual_channel, tmp_path,
                                                             capsys):
    """The generic file names no vendor: it may fit a drive of any vendor. The node of
    another vendor is told it, not to add a file that is in the folder."""
    sim_segment_factory([4], eds_path=str(VENDOR_A), identities={4: STRANGER})
    folder = _only(tmp_path, PROJECT_EDS / "cia402_drive.eds", VENDOR_A)
    assert _run(tmp_path, virtual_channel, folder, out=None) == 1
    err = capsys.readouterr().err
    assert "add its EDS/DCF" not in err and "may fit: cia402_drive.eds (it names no vendor" \
        in err, err
    assert "vendor_a.eds" not in err  # vendor 0xAA's: not for vendor 0xBB, not offered


def test_no_file_that_could_fit_still_asks_for_one(sim_segment_factory, virtual_channel,
                                                  tmp_path, capsys):
    sim_segment_factory([4], eds_path=str(VENDOR_A), identities={4: STRANGER})
    assert _run(tmp_path, virtual_channel, _only(tmp_path, VENDOR_A), out=None) == 1
    err = capsys.readouterr().err
    assert "for vendor 0x000000BB product 0x00000001: add its EDS/DCF" in err, err


def test_the_default_sim_and_the_projects_own_eds_folder_make_a_config_that_runs(
        sim_segment_factory, virtual_channel, tmp_path, capsys):
    """`rocoma-can sim` emulates eds/cia402_drive.eds (vendor 0: none); init-config with
    --eds-dir eds matched nothing, so docs/first-robot.md could not be followed from a
    checkout. The file names no vendor and neither do the drives, and its product is
    theirs: it is the file made for them (the manager's own EDS beside it is no drive's)."""
    sim_segment_factory([1, 2, 3])
    assert _run(tmp_path, virtual_channel, PROJECT_EDS) == 0, capsys.readouterr()
    text = (tmp_path / "robot.yaml").read_text()
    config = yaml.safe_load(text)
    assert [(d["node_id"], Path(d["eds"]).name) for d in config["drives"]] == [
        (1, "cia402_drive.eds"), (2, "cia402_drive.eds"), (3, "cia402_drive.eds")]
    assert config["drives"][0]["identity"] == {"vendor_id": 0, "product_code": 0x402,
                                               "revision": 0x10000, "serial": 1}
    assert "rocoma_manager.eds" not in text
    capsys.readouterr()
    assert main(["check-config", str(tmp_path / "robot.yaml")]) == 0, capsys.readouterr()
    status = bring_up(tmp_path / "robot.yaml")
    assert [s.phase for s in status] == ["READY"] * 3, status


@pytest.mark.parametrize("file_vendor, file_product, found, verdict", [
    (0xAA, 0x1234, Identity(0xAA, 0x1234, 1, 1), "made"),
    (0xAA, 0x1234, Identity(0xAA, 0x9999, 1, 1), "wrong"),
    (0xAA, 0x1234, Identity(0xBB, 0x1234, 1, 1), "wrong"),
    (0xAA, None, Identity(0xAA, 0x9999, 1, 1), "may"),
    (0xAA, None, Identity(0xBB, 0x9999, 1, 1), "wrong"),
    (None, 0x402, Identity(0, 0x402, 1, 1), "made"),
    (None, 0x402, Identity(0xAA, 0x402, 1, 1), "may"),
    (None, None, Identity(0xAA, 0x1, 1, 1), "may"),
    (0xAA, 0x1234, Identity(0xAA, None, 1, 1), "may"),   # the device keeps its product
])
def test_init_config_offers_no_file_bring_up_would_refuse(tmp_path, file_vendor,
                                                          file_product, found, verdict):
    """One rule: a file init-config would write for a device is one bring-up accepts for
    it (identity.IdentityCheck with the file's vendor and product), and every file bring-up
    accepts is made for it or offered."""
    from rocoma_can.cli.device_match import index_device_files, match
    from rocoma_can.drivers.files.device_file import read_device_file
    from rocoma_can.drivers.files.identity import IdentityCheck
    vendor, product = f"0x{file_vendor or 0:08X}", f"0x{file_product or 0:08X}"
    text = VENDOR_A.read_text().replace("=0x000000AA", f"={vendor}")  # [DeviceInfo], 0x1018
    text = text.replace("=0x00001234", f"={product}")
    folder = _only(tmp_path)
    (folder / "drive.eds").write_text(text)
    files, _ = index_device_files(str(folder))
    made, may = match(1, found, 0x20192, files)
    got = "made" if made else "may" if may else "wrong"
    assert got == verdict
    od = read_device_file(str(folder / "drive.eds")).object_dictionary(1)
    refused = IdentityCheck.of(None, od, "drive.eds").problem(found)
    assert (refused is not None) == (verdict == "wrong"), refused


def test_eds_picks_a_file_bring_up_would_refuse_is_refused(sim_segment_factory,
                                                           virtual_channel, tmp_path, capsys):
    sim_segment_factory([1], eds_path=str(VENDOR_A), identities={1: STRANGER})
    assert _run(tmp_path, virtual_channel, None, "--eds", f"1={VENDOR_A}", out=None) == 1
    err = capsys.readouterr().err
    assert "node 1: --eds vendor_a.eds: vendor_id 0x000000BB, product_code 0x00000001 " \
           "found, its file vendor_a.eds is for vendor_id 0x000000AA, product_code " \
           "0x00001234: wrong file or wrong drive?" in err, err


@pytest.mark.parametrize("value, said", [
    ("1", "--eds: expected NODE=FILE"),
    ("0=x.eds", "--eds: 0=x.eds: node ids are 1..127"),
    ("1=missing.eds", "--eds 1=missing.eds: not read"),
])
def test_eds_usage_errors_exit_2_before_the_scan(virtual_channel, capsys, value, said):
    started = time.monotonic()
    try:
        code = main(["init-config", "--interface", "virtual", "--channel", virtual_channel,
                     "--eds", value])
    except SystemExit as usage:  # argparse's own, for a value it cannot parse
        code = usage.code
    assert code == 2
    assert time.monotonic() - started < 1.0  # the scan alone takes longer
    assert said in capsys.readouterr().err


def test_neither_eds_dir_nor_eds_is_a_usage_error(virtual_channel, capsys):
    assert main(["init-config", "--interface", "virtual", "--channel", virtual_channel]) == 2
    assert "--eds-dir DIR or --eds NODE=FILE" in capsys.readouterr().err


def test_two_devices_at_one_node_id_are_not_configured(sim_segment_factory, virtual_channel,
                                                       tmp_path, capsys):
    sim_segment_factory([1, 2], eds_path=str(VENDOR_A))
    sim_segment_factory([1], eds_path=str(VENDOR_A), identities={1: Identity(serial=0x77)})
    assert _run(tmp_path, virtual_channel, _only(tmp_path, VENDOR_A)) == 0
    text = (tmp_path / "robot.yaml").read_text()
    assert [d["node_id"] for d in yaml.safe_load(text)["drives"]] == [2]
    assert "# node 1: two or more devices answer at node id 1: not configured (give each " \
           "its own node id: rocoma-can lss)" in text


# -- file names that are not UTF-8; an output that exists ------------------------------------

def test_a_matching_file_whose_name_is_not_utf8_is_a_note_not_a_traceback(
        sim_segment_factory, virtual_channel, tmp_path, capsys):
    """A YAML config is UTF-8 text: it cannot name such a file, and the generated one with
    it in a comment was refused by the YAML reader (ReaderError traceback)."""
    sim_segment_factory([1], eds_path=str(VENDOR_A))
    folder = _only(tmp_path)
    (Path(os.fsdecode(bytes(folder) + b"/vendor_\xff.eds"))).write_bytes(VENDOR_A.read_bytes())
    assert _run(tmp_path, virtual_channel, folder) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "note: vendor_\\xff.eds: its name is not UTF-8: a config (UTF-8 text) cannot " \
           "name it; rename it" in err, err
    # the node's own line: not only "add its EDS/DCF", when a file in DIR was not read
    assert ": add its EDS/DCF (or fix a file init-config noted as not read) and run init-config " \
           "again" in err, err
    shutil.copy(VENDOR_A, folder)  # the same file under a name a config can hold
    assert _run(tmp_path, virtual_channel, folder) == 0, capsys.readouterr()


def test_an_output_that_exists_is_refused_unless_forced_and_then_kept(
        sim_segment_factory, virtual_channel, tmp_path, capsys):
    """A hand-edited robot.yaml was silently replaced. Refused (exit 2, before the scan);
    with --force replaced, the old one kept beside it as robot.yaml.bak (then .bak.1), and
    said."""
    sim_segment_factory([1], eds_path=str(VENDOR_A))
    folder = _only(tmp_path, VENDOR_A)
    edited = tmp_path / "robot.yaml"
    edited.write_text("# my robot, by hand\n")
    started = time.monotonic()
    assert _run(tmp_path, virtual_channel, folder) == 2
    assert time.monotonic() - started < 1.0  # refused before the scan
    err = capsys.readouterr().err.strip()
    assert err == (f"rocoma-can: init-config: -o {edited}: exists (a config edited by hand "
                   "would be lost): --force replaces it, keeping it as robot.yaml.bak"), err
    assert edited.read_text() == "# my robot, by hand\n"
    assert _run(tmp_path, virtual_channel, folder, "--force") == 0
    assert f"{edited} existed: kept as {tmp_path}/robot.yaml.bak" in capsys.readouterr().err
    assert (tmp_path / "robot.yaml.bak").read_text() == "# my robot, by hand\n"
    assert yaml.safe_load(edited.read_text())["drives"]
    first = edited.read_text()
    assert _run(tmp_path, virtual_channel, folder, "--force") == 0
    assert (tmp_path / "robot.yaml.bak.1").read_text() == first  # no backup overwritten
    assert (tmp_path / "robot.yaml.bak").read_text() == "# my robot, by hand\n"
