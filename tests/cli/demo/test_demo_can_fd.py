"""rocoma_can/cli/demo/walkthrough.py, config.py (``--fd``): the demo on CAN FD buses, FD frames
both ways; its CAN FD options checked; twelve drives at 2 kHz fit its CAN FD buses and not classic
ones."""
from __future__ import annotations

import copy

import pytest

from rocoma_can.cli.demo.walkthrough import DemoOptions, Walkthrough
from rocoma_can.cli.main import main


def test_demo_on_can_fd_buses_passes_with_fd_frames_both_ways(virtual_channel):
    """--fd: the walk-through on CAN FD buses, every PDO an FD frame with bit rate switching
    both ways, each drive's targets in one RPDO and its feedback in one TPDO (12 bytes on
    the wire each: 9 mapped in the RPDO, padded as an FD frame is), the load said."""
    from fixtures.bus import record
    recorders = [record(f"{virtual_channel}-{k}", "inproc", fd=True) for k in range(2)]
    lines: list[str] = []
    try:
        report = Walkthrough(DemoOptions(drives=6, rate=200.0, duration=3.0, buses=2,
                                         data_bitrate=5_000_000, channel=virtual_channel),
                             out=lines.append).run()
    finally:
        for r in recorders:
            r.stop()
    assert report.ok, "\n".join(lines)
    assert lines[0].startswith("rocoma-can demo: the busiest bus: 3 drives at 200 Hz need "
                               "1,400 frames/s") and "CAN FD bus (1/5 Mbit/s)" in lines[0]
    assert "2 inproc CAN FD buses" in lines[1]
    for r in recorders:
        drives = r.frames(where=lambda f: f.cob_id & 0x7F in (1, 2, 3))  # each bus's nodes
        rpdos = [f for f in drives if f.cob_id & 0x780 in (0x200, 0x300, 0x400, 0x500)]
        tpdos = [f for f in drives if f.cob_id & 0x780 in (0x180, 0x280, 0x380, 0x480)]
        assert {f.cob_id for f in rpdos} == {0x201, 0x202, 0x203}  # RPDO2 (0x30n) unused
        assert {f.cob_id for f in tpdos} == {0x181, 0x182, 0x183}
        assert {len(f.data) for f in rpdos + tpdos} == {12}
        assert all(f.message.is_fd and f.message.bitrate_switch for f in rpdos + tpdos)


def test_demo_cli_checks_can_fd_options(capsys):
    assert main(["demo", "--data-bitrate", "2000000", "--no-record"]) == 2
    assert main(["demo", "--fd", "--data-bitrate", "200000", "--no-record"]) == 2
    assert capsys.readouterr().out.splitlines() == [
        "demo: --data-bitrate: the data phase of --fd buses, 1000000..15000000 bit/s, got "
        "2000000 without --fd",
        "demo: --data-bitrate: the data phase of --fd buses, 1000000..15000000 bit/s, got "
        "200000"]


def test_twelve_drives_at_2khz_fit_the_demos_can_fd_buses_and_not_classic_ones():
    """The demo's default split (a bus per three drives) at 2 kHz: its CAN FD buses (1/5
    Mbit/s, PDOs up to 64 bytes) carry it, checked as real buses; 1 Mbit/s classic buses
    are refused with what fits, and so are FD buses with 8-byte PDOs (13 frames a cycle).
    The classic demo's in-process buses have no bit rate: it runs, and says so once."""
    from rocoma_can.cli.demo.config import default_buses, demo_config
    from rocoma_can.cli.demo.walkthrough import _load_line
    from rocoma_can.runtime.config import ConfigError, validate
    fd = demo_config("demo-bus", 12, 2000.0, default_buses(12), "inproc",
                     data_bitrate=5_000_000)
    config = validate(fd, source="demo")
    assert len(config.loads) == 4 and all(
        lo.drives == 3 and lo.frames_per_cycle == 7 and lo.load < 1.0
        and lo.drives_that_fit == 3 for lo in config.loads.values())
    classic = copy.deepcopy(fd)
    for b in classic["buses"]:
        del b["fd"], b["data_bitrate"]
    for d in classic["drives"]:
        del d["pdo_bytes"]
    with pytest.raises(ConfigError) as info:
        validate(classic, source="demo")
    assert info.value.problems == [
        f"demo: buses[{k}] (bus{k}): bus overload: 3 drives at 2000 Hz need 26,000 frames/s "
        "(269% of the bus, worst case); a 1 Mbit/s bus carries ~7,407 8-byte frames/s worst "
        "case; 743 Hz fits 3 drives, 2000 Hz fits 1" for k in range(4)]
    short = copy.deepcopy(fd)
    for d in short["drives"]:
        del d["pdo_bytes"]
    with pytest.raises(ConfigError, match="need 26,000 frames/s .129% of the bus"):
        validate(short, source="demo")
    unchecked = validate(demo_config("demo-bus", 12, 2000.0, 4, "inproc"), source="demo")
    assert unchecked.loads == {}
    assert _load_line(unchecked) == (
        "  note: 1 Mbit/s classic buses would not carry this (bus0: 3 drives at 2000 Hz need "
        "26,000 frames/s (269% of the bus, worst case); a 1 Mbit/s bus carries ~7,407 8-byte "
        "frames/s worst case; 743 Hz fits 3 drives, 2000 Hz fits 1); the in-process ones do "
        "(--fd: CAN FD buses, checked as real ones)")
