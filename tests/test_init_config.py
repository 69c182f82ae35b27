"""`rocoma-can init-config`: a config from a scan of simulated drives and a folder of
device files, through the real CLI: each node matched to its file by vendor and product, the
identity it was seen with carried into the config, the rest as comments; the output passes
check-config and runs.

The tests taking ``sim_interface`` run on python-can's virtual bus and again on SocketCAN
vcan0 (the vcan suite, through tools/vcan-run)."""
from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import pytest
import yaml
from fixtures.budgets import GUEST_STALL, STALL
from fixtures.bus import scan_bus_args
from fixtures.running import DEMO_RUN, DEMO_WAIT

from rocoma_can.cli.main import main
from rocoma_can.drivers.identity import Identity
from rocoma_can.runtime.config import validate
from rocoma_can.runtime.system import Runtime

EDS = Path(__file__).parent / "fixtures" / "eds"
VENDOR_A = EDS / "vendor_a.eds"  # vendor 0xAA, product 0x1234 in its [DeviceInfo]
STRANGER = Identity(vendor_id=0xBB, product_code=0x1)


def _folder(tmp_path: Path) -> Path:
    """The drives' files as a person keeps them: the vendor's, and one that is for no
    vendor (the generic CiA 402 file, which must match nothing)."""
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
    assert "no file in" in text and "for vendor 0x000000BB product 0x00000001" in text
    assert "increments_per_rev not in its file: a guess" in text  # no 0x608F in the file
    assert config["bus"] == {"interface": sim_interface, "channel": channel,
                             "bitrate": 1_000_000}
    assert config["manager"]["node_id"] not in (1, 2, 3)
    assert config["manager"]["estop_must_be_cleared"] is True
    capsys.readouterr()
    assert main(["check-config", str(out)]) == 0, capsys.readouterr()


def _bring_up(path: Path) -> list:
    """The config as `run` starts it (at 100 Hz), until bring-up has finished: each drive's
    status then."""
    config = yaml.safe_load(path.read_text())
    config["rate"] = 100  # as `run --rate 100`: the loop's rate is not what is tested
    status = []
    with Runtime(validate(config, str(path), path.parent)) as rt:
        def operate() -> None:
            deadline = time.monotonic() + DEMO_WAIT
            while any(s.phase not in ("READY", "FAILED") for s in rt.hardware.drive_status()) \
                    and time.monotonic() < deadline:  # NOT_STARTED, then bring-up
                time.sleep(0.01)
            status.extend(rt.hardware.drive_status())
            rt.loop.stop("test")

        t = threading.Thread(target=operate)
        t.start()
        rt.run(duration=DEMO_RUN, signals=False)
        t.join(DEMO_WAIT)
    return status


def test_the_generated_config_runs(sim_segment_factory, virtual_channel, tmp_path):
    """What init-config writes is a config the runtime brings up as it is (the identities
    it carries are the drives' own)."""
    sim_segment_factory([1, 2], eds_path=str(VENDOR_A))
    out, _ = _init_config(tmp_path, "virtual", virtual_channel)
    status = _bring_up(out)
    assert [(s.node_id, s.phase) for s in status] == [(1, "READY"), (2, "READY")], status


def test_a_swapped_drive_is_refused_by_the_config_init_config_wrote(
        sim_segment_factory, virtual_channel, tmp_path):
    """The config remembers which drive was at which node id: against a bus where nodes 1
    and 2 swapped their drives, bring-up refuses both and says why."""
    segment = sim_segment_factory([1, 2], eds_path=str(VENDOR_A))
    out, _ = _init_config(tmp_path, "virtual", virtual_channel)
    segment.drives[1].swap(Identity(serial=2))
    segment.drives[2].swap(Identity(serial=1))
    status = _bring_up(out)
    assert [s.phase for s in status] == ["FAILED", "FAILED"], status
    assert "serial 0x00000001 expected, 0x00000002 found: swapped node ids or cables?" \
        in str(status[0].fault), status


def test_no_drive_to_configure_and_usage_errors(sim_segment_factory, virtual_channel,
                                                 tmp_path, capsys):
    sim_segment_factory([4], eds_path=str(VENDOR_A), identities={4: STRANGER})
    args = [*scan_bus_args("virtual", virtual_channel, STALL), "--eds-dir",
            str(_folder(tmp_path))]
    assert main(["init-config", *args]) == 1  # found a node, but no file for it
    err = capsys.readouterr().err
    assert "no drive could be configured" in err and "vendor 0x000000BB" in err
    assert main(["init-config", *args[:-1], str(tmp_path / "missing")]) == 2
    assert "not a directory" in capsys.readouterr().err
    with pytest.raises(SystemExit) as usage:
        main(["init-config", "--channel", virtual_channel])  # no --eds-dir
    assert usage.value.code == 2


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
