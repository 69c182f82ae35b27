"""rocoma_can/runtime/bus_load.py, config_check.py (the buses): the bus-load arithmetic, classic and
CAN FD, several buses each with its drives, and the COB-IDs that must be free on each bus."""
from __future__ import annotations

from pathlib import Path

import pytest
from fixtures.configs import good
from fixtures.paths import ROOT

from rocoma_can.drivers.hardware import CanopenHardware
from rocoma_can.drivers.plan.config import DriveConfig
from rocoma_can.drivers.protocol.wire import frame_bits
from rocoma_can.runtime.bus_load import bus_load
from rocoma_can.runtime.config import ConfigError, validate


def test_frame_bits_match_the_reference():
    assert frame_bits(8, worst_case=False) == 111
    assert frame_bits(8) == 135
    assert frame_bits(0, worst_case=False) == 47
    assert round(1_000_000 / frame_bits(8)) == 7407


def _drives(n: int, **kw) -> list[DriveConfig]:
    return [DriveConfig(f"j{i}", i, 4096, 1.0, **kw) for i in range(1, n + 1)]


def test_bus_load_counts_the_driver_layouts():
    # CSP, feedback position+velocity+torque: 1 RPDO of 7 bytes, TPDOs of 8 + 4 bytes.
    load_ = bus_load(_drives(3), 1000, 1_000_000)
    assert load_.frames_per_cycle == 3 * 3 + 1
    assert load_.bits_per_cycle == frame_bits(0) + 3 * (frame_bits(7) + frame_bits(8)
                                                         + frame_bits(4))
    # one RPDO + one TPDO of 8 bytes per drive, as in the reference's capacity table
    two = bus_load(_drives(9, feedback=("position", "torque"), modes=("csp",)), 400, 1_000_000)
    assert two.frames_per_cycle == 19 and two.load < 1.0


def test_overload_says_what_fits():
    cfg = good()
    cfg["rate"] = 1000
    cfg["drives"] = [{"name": f"j{i}", "node_id": i, "increments_per_rev": 4096,
                      "rated_torque_nm": 1.0} for i in range(1, 13)]
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    (problem,) = info.value.problems
    assert "rate: bus overload" in problem
    assert "12 drives at 1000 Hz need 37,000 frames/s" in problem
    assert "~7,407 8-byte frames/s worst case" in problem
    assert "fits 12 drives" in problem and "1000 Hz fits 2" in problem


def test_virtual_bus_has_no_bitrate_limit():
    cfg = good()
    cfg["bus"] = {"interface": "virtual", "channel": "x"}
    cfg["rate"] = 5000
    assert validate(cfg).loads == {}


def four_buses() -> dict:
    """12 drives at 1 kHz on four 1 Mbit/s buses, three drives each, node ids 1-3 on each;
    one RPDO and one TPDO per drive (position and torque feedback: with velocity too, a
    second TPDO makes 10 frames per cycle, 10,000 frames/s, over a bus's ~7,400). Without
    velocity feedback the controllers are ones that need none: a CSP pd (the drive's own
    loop) and hold in CSP as the emergency controller (damp needs velocity)."""
    cfg = good()
    cfg["controllers"] = [{"name": "stand", "plugin": "pd", "emergency": "hold",
                           "params": {"mode": "CSP"}}]
    cfg["emergency_controllers"] = [{"name": "hold", "plugin": "hold",
                                     "params": {"mode": "CSP"}}]
    del cfg["bus"]
    cfg["rate"] = 1000
    cfg["buses"] = [{"name": limb, "interface": "socketcan", "channel": f"can{k}",
                     "bitrate": 1_000_000} for k, limb in enumerate(("lf", "rf", "lh", "rh"))]
    cfg["drives"] = [{"name": f"{limb}{n}", "node_id": n, "bus": limb,
                      "increments_per_rev": 4096, "rated_torque_nm": 1.0,
                      "feedback": ["position", "torque"]}
                     for limb in ("lf", "rf", "lh", "rh") for n in (1, 2, 3)]
    return cfg


def test_several_buses_each_with_its_drives_and_load():
    config = validate(four_buses())
    assert [b.label for b in config.buses] == ["lf", "rf", "lh", "rh"]
    assert [b.channel for b in config.buses] == ["can0", "can1", "can2", "can3"]
    assert [d.name for d in config.drives_on(config.buses[2])] == ["lh1", "lh2", "lh3"]
    assert set(config.loads) == {"lf", "rf", "lh", "rh"}
    assert all(load_.drives == 3 and load_.load < 1.0 for load_ in config.loads.values())
    assert config.node_bus.label == "lf"  # manager.bus not given: the first bus


def test_twelve_drives_at_1khz_overload_one_bus_but_fit_on_four():
    cfg = four_buses()
    for d in cfg["drives"]:
        d["bus"] = "lf"
        d["node_id"] = len([x for x in cfg["drives"] if x is not d and "seen" in x]) + 1
        d["seen"] = True
    for d in cfg["drives"]:
        del d["seen"]
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    (problem,) = info.value.problems
    assert "buses[0] (lf): bus overload" in problem and "12 drives at 1000 Hz" in problem


@pytest.mark.parametrize("label, edit, expected", [
    ("both", lambda c: c.update(bus={"channel": "can0"}),
     "bus, buses: give one bus as bus: or several as buses:, not both"),
    ("unnamed", lambda c: c["buses"][1].pop("name"), "buses[1].name: expected the bus's name"),
    ("twice", lambda c: c["buses"][1].update(name="lf"), "buses[1].name: 'lf' is already buses[0]"),
    ("no such bus", lambda c: c["drives"][0].update(bus="tail"),
     "drives[0].bus: no bus named 'tail' (buses: 'lf', 'rf', 'lh', 'rh')"),
    ("same node id on a bus", lambda c: c["drives"][1].update(node_id=1),
     "drives[1].node_id: 1 is already used by drives[0] on bus 'lf'"),
    ("manager bus", lambda c: c["manager"].update(bus="tail"),
     "manager.bus: expected the name of one of the buses"),
    ("data bitrate without fd", lambda c: c["buses"][0].update(data_bitrate=5_000_000),
     "buses[0].data_bitrate: only for a CAN FD bus (fd: true)"),
    ("fd not a bool", lambda c: c["buses"][0].update(fd="yes"), "buses[0].fd: expected true"),
])
def test_bus_problems_name_their_path(label, edit, expected):
    cfg = four_buses()
    edit(cfg)
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert any(expected in p for p in info.value.problems), info.value.problems


def test_the_estop_cob_id_must_be_free_on_every_bus():
    """0x0A0 is also the EMCY of node 32: an RTR e-stop would be dropped as a short EMCY, an
    EMCY of that drive taken for an e-stop. Same for a TPDO/RPDO id or the manager's own."""
    cfg = four_buses()
    cfg["drives"][4]["node_id"] = 32
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert any("manager.estop_cob_id: 0x0A0 is the EMCY of node 32 (drive 'rf2')" in p
               for p in info.value.problems), info.value.problems
    cfg = four_buses()
    cfg["manager"]["estop_cob_id"] = 0x181
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert any("0x181 is TPDO1 of node 1" in p for p in info.value.problems)
    cfg["manager"]["estop_cob_id"] = 0x080 + 100
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert any("the EMCY of node 100, the manager's own" in p for p in info.value.problems)


def _absolute_cob_ids(tmp_path: Path, tpdo1: int = 0x181, rpdo1: int = 0x201) -> str:
    """The generic drive's EDS with absolute PDO COB-IDs (as a DCF made for node 1 has)."""
    text = (ROOT / "eds" / "cia402_drive.eds").read_text()
    text = text.replace("DefaultValue=$NODEID+0x180", f"DefaultValue=0x{tpdo1:X}", 1)
    text = text.replace("DefaultValue=$NODEID+0x200", f"DefaultValue=0x{rpdo1:X}", 1)
    path = tmp_path / "node1.dcf.eds"
    path.write_text(text)
    return str(path)


def test_pdo_cob_ids_from_a_file_must_not_clash_on_a_bus(tmp_path):
    """One file with absolute COB-IDs for two drives: drive 1 would take drive 2's RPDOs
    (its enable and targets) and its TPDOs would be decoded as drive 2's feedback."""
    cfg = good()
    for d in cfg["drives"]:
        d["eds"] = _absolute_cob_ids(tmp_path)
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    said = " | ".join(info.value.problems)
    assert "TPDO1 of drive 'j2': COB-ID 0x181 (from its EDS/DCF) is also TPDO1 of drive " \
           "'j1' on the same bus" in said, said
    assert "RPDO1 of drive 'j2': COB-ID 0x201" in said, said
    # the library refuses it too, before it opens anything
    drives = [DriveConfig(f"j{i}", i, 4096, 1.0, eds=_absolute_cob_ids(tmp_path))
              for i in (1, 2)]
    with pytest.raises(ValueError, match="also TPDO1 of drive 'j1'"):
        CanopenHardware(None, drives, 100, 0.01)  # type: ignore[arg-type]


def test_a_bare_base_cob_id_in_a_file_is_the_predefined_one(tmp_path):
    """0x180 for TPDO1 ("node 0") in a vendor's EDS means 0x180 + node id, as the drive
    uses it after power-on: two drives on one file do not clash."""
    cfg = good()
    for d in cfg["drives"]:
        d["eds"] = _absolute_cob_ids(tmp_path, tpdo1=0x180, rpdo1=0x200)
    config = validate(cfg)
    assert [config.plans[f"j{n}"].layout.tpdos[0].cob_id for n in (1, 2)] == [0x181, 0x182]
    assert [config.plans[f"j{n}"].layout.rpdos[0].cob_id for n in (1, 2)] == [0x201, 0x202]


@pytest.mark.parametrize("tpdo1, clash", [
    (0x080, "reserved for NMT, SYNC, SDO or heartbeat frames"),
    (0x0A0, "also the e-stop frame (manager.estop_cob_id)"),
    (0x082, "also the EMCY of drive 'j2'"),
    (0x1E4, "also the manager's state frame (TPDO1)"),
])
def test_a_pdo_cob_id_from_a_file_must_not_be_taken_or_reserved(tmp_path, tpdo1, clash):
    cfg = good()
    cfg["drives"][0]["eds"] = _absolute_cob_ids(tmp_path, tpdo1=tpdo1)
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert any(f"TPDO1 of drive 'j1': COB-ID 0x{tpdo1:03X}" in p and clash in p
               for p in info.value.problems), info.value.problems


def test_one_wire_is_one_bus():
    cfg = four_buses()
    cfg["buses"][3]["channel"] = "can0"
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert any("buses[3].channel: socketcan:can0 is already buses[0]" in p
               for p in info.value.problems), info.value.problems


def test_node_ids_may_repeat_across_buses():
    config = validate(four_buses())
    assert sorted(d.node_id for d in config.drives) == [1] * 4 + [2] * 4 + [3] * 4


def test_can_fd_frames_are_shorter_on_the_wire():
    """CAN FD with bit rate switching: the data phase at 5 Mbit/s makes an 8-byte frame
    take about half the time of a classic one at 1 Mbit/s (arbitration stays at 1 Mbit/s),
    so one FD bus carries eight drives at 1 kHz (a classic one: three)."""
    classic, fd = frame_bits(8), frame_bits(8, data_ratio=1_000_000 / 5_000_000)
    assert 0.35 < fd / classic < 0.6
    assert frame_bits(8, data_ratio=1.0) > classic  # FD without switching: a longer CRC
    cfg = four_buses()
    cfg["buses"] = [{"name": "all", "channel": "can0", "bitrate": 1_000_000, "fd": True,
                     "data_bitrate": 5_000_000}]
    cfg["drives"] = [{"name": f"j{n}", "node_id": n, "increments_per_rev": 4096,
                      "rated_torque_nm": 1.0, "feedback": ["position", "torque"]}
                     for n in range(1, 9)]
    config = validate(cfg)
    (load_,) = config.loads.values()
    assert load_.load < 1.0 and "CAN FD bus (1/5 Mbit/s)" in load_.explain()
    assert load_.drives_that_fit == 8
    assert config.bus.fd and config.bus.data_bitrate == 5_000_000
    cfg["buses"][0].update(fd=False, data_bitrate=None)
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert "1000 Hz fits 3" in info.value.problems[0]


def test_longer_pdos_on_can_fd_make_fewer_frames_and_need_an_fd_bus():
    """pdo_bytes 64 (drives that map CANopen FD PDOs): one RPDO and one TPDO per drive. On
    a 1/5 Mbit/s FD bus three drives with position, velocity and torque feedback fit at
    2 kHz that way (8-byte PDOs make 10 frames a cycle, which do not: each frame's
    arbitration runs at the nominal rate whatever it carries); on a classic bus the key
    is an error that says why."""
    cfg = four_buses()
    cfg["rate"] = 2000
    cfg["buses"] = [{**b, "fd": True, "data_bitrate": 5_000_000} for b in cfg["buses"]]
    for d in cfg["drives"]:
        d.pop("feedback")  # every feedback: 12 bytes, two 8-byte TPDOs
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert "3 drives at 2000 Hz need 20,000 frames/s (102% of the bus" in info.value.problems[0]
    for d in cfg["drives"]:
        d["pdo_bytes"] = 64
    config = validate(cfg)
    assert all(lo.frames_per_cycle == 7 and lo.load < 1.0 and lo.drives_that_fit == 3
               for lo in config.loads.values())
    cfg["buses"][1].update(fd=False, data_bitrate=None)
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert info.value.problems[:3] == [
        f"<memory>: drives[{k}].pdo_bytes: 64 bytes a PDO need a CAN FD bus (fd: true), and "
        "bus 'rf' is classic CAN (8 bytes a frame)" for k in (3, 4, 5)]


def test_an_in_process_bus_with_a_bitrate_is_checked_as_the_bus_it_stands_for():
    cfg = good()
    cfg["bus"] = {"interface": "inproc", "channel": "x", "bitrate": 1_000_000}
    cfg["rate"] = 5000
    with pytest.raises(ConfigError, match="rate: bus overload: 2 drives at 5000 Hz"):
        validate(cfg)
    cfg["rate"] = 1000
    assert validate(cfg).loads["x"].load < 1.0
