"""drivers/files/device_file.py, capabilities.py, rocoma_can/cli/demo/ (``--eds``): each
vendor-like file (tests/fixtures/eds/) runs: bring-up, tracking and torque-off on the bus, the
demo's walk-through, canopen's own CiA 402 master on the simulated variant, and a controller that
needs feedback a file lacks refused at load."""
from __future__ import annotations

import os
import struct
from pathlib import Path

import canopen
import pytest
from fixtures.driver_rig import INCREMENTS_PER_REV, VIRTUAL, Rig
from fixtures.paths import EDS
from fixtures.rig_controllers import Sine

from rocoma_can import ManagerState, SwitchResult
from rocoma_can.drivers.files.device_file import read_device_file
from rocoma_can.drivers.protocol import cia301, cia402
from rocoma_can.drivers.protocol.cia402 import State402
from rocoma_can.drivers.protocol.joints import JointMode

# --- bring-up, a cyclic command, e-stop -> torque-off, per file -------------------------------


DRIVABLE = {
    "fixed_pdo.eds": dict(node=1),
    "no_abort_option.eds": dict(node=1),
    "commissioned.dcf": dict(node=5, increments_per_rev=0x40000),
    "minimal.eds": dict(node=1),
    "hand_written.eds": dict(node=1),
    "node1_baked.dcf": dict(node=3, increments_per_rev=0x40000),  # exported for node 1
    "tight_od.eds": dict(node=2, modes=("ip",)),
    "fixed_split.eds": dict(node=1),
    "guarded.eds": dict(node=1),  # node guarding only
}


@pytest.mark.parametrize("file", sorted(DRIVABLE))
def test_bring_up_track_and_torque_off_on_each_file(file, sim_segment_factory, bus_factory,
                                                    frame_recorder, virtual_channel):
    info = DRIVABLE[file]
    node, increments = info["node"], info.get("increments_per_rev", INCREMENTS_PER_REV)
    segment = sim_segment_factory([node], eds_path=str(EDS / file),
                                  increments_per_rev=increments)
    recorder = frame_recorder(virtual_channel)
    rig = Rig.for_setup(bus_factory(), [node], VIRTUAL, modes=info.get("modes", ("csp",)),
                        drive={"eds": str(EDS / file), "increments_per_rev": increments})
    try:
        budget = VIRTUAL.bring_up_budget(1)
        assert rig.run_until(lambda: not rig.hw.starting, budget), rig.hw.drive_status()
        assert rig.hw.all_ready, rig.hw.drive_status()
        sim = segment.drives[node]
        assert sim.nmt_state == cia301.NmtState.OPERATIONAL
        if rig.hw.plans[0].guarded:  # watches us: by life guarding, or the heartbeat
            assert sim.od_value(cia301.LIFE_TIME_FACTOR) > 0 and sim.nmt.guard_requests > 0
        else:
            assert sim.od_value(cia301.CONSUMER_HEARTBEAT_TIME, 1) >> 16 == 100
        rig.mgr.add_controller(Sine("sine", JointMode.CSP, amplitude=0.2))
        assert rig.switch("sine") == SwitchResult.SWITCHED
        assert rig.run_until(lambda: rig.hw.all_enabled, VIRTUAL.enable_budget()), \
            rig.hw.drive_status()
        rig.run(0.5)
        assert rig.mgr.state == ManagerState.OK and sim.state402 == State402.OPERATION_ENABLED
        assert abs(sim.position_rad) > 0.01  # it moved as commanded
        rpdo = rig.hw.layouts[0].rpdos[0]
        mark = recorder.mark()
        rig.mgr.emergency_stop("test")  # no emergency controller: FAILPROOF
        rig.run(10 * rig.dt)
        assert rig.states[-1] == ManagerState.FAILPROOF
        frames = recorder.wait_for_count(5, VIRTUAL.stall, rpdo.cob_id, since=mark)
        controlwords = [struct.unpack_from("<H", f.data)[0] for f in frames]
        assert controlwords[-1] == 0 and len(frames[-1].data) == rpdo.size
        assert rig.run_until(lambda: sim.state402 == State402.SWITCH_ON_DISABLED,
                             VIRTUAL.detect_budget())
    finally:
        rig.close()


@pytest.mark.parametrize("file", sorted(p.name for p in EDS.iterdir()))
def test_the_demo_walks_through_on_each_file(file):
    """`rocoma-can demo --eds FILE`: the modes the file supports, the steps it cannot do
    skipped with the reason, and every step that runs passes."""
    from rocoma_can.cli.demo.walkthrough import DemoOptions, Walkthrough
    lines: list[str] = []
    report = Walkthrough(DemoOptions(drives=2, rate=100.0, duration=2.0, eds=str(EDS / file)),
                         out=lines.append).run()
    assert report.ok, "\n".join(lines)
    assert lines[0].startswith(f"rocoma-can demo: the drives emulate {EDS / file}")
    assert report.steps[-1].name == "loop stop -> torque-off frames"
    if file == "commissioned.dcf":  # one node's file: from that node on, COB-IDs re-derived
        assert "  note: a DCF of node 5: the drives from node 5 on, each with its COB-IDs " \
            "re-derived" in lines


def test_the_demo_says_why_it_cannot_use_a_file(tmp_path, capsys):
    from rocoma_can.cli.main import main
    velocity_only = tmp_path / "pv_only.eds"
    velocity_only.write_text((EDS / "minimal.eds").read_text().replace(
        "DefaultValue=0x00000180", "DefaultValue=0x00000100"))  # CSV only
    assert main(["demo", "--eds", str(velocity_only)]) == 2
    assert "no position mode the demo's controllers can use" in capsys.readouterr().out
    demo_dirs = Path(os.environ["XDG_STATE_HOME"]) / "rocoma-can" / "demo"
    assert not list(demo_dirs.iterdir())  # it did not run: no empty recording left behind


@pytest.mark.parametrize("file", sorted(p.name for p in EDS.iterdir()))
def test_canopens_own_cia402_master_walks_each_simulated_variant(file, sim_segment_factory,
                                                                bus_factory):
    """canopen's BaseNode402 (a CiA 402 master nobody here wrote) reads the simulated drive's
    PDO configuration by SDO, then walks it to OPERATION ENABLED and back through its PDOs."""
    from canopen.profiles.p402 import BaseNode402
    node_id = 5 if file.endswith(".dcf") else 1
    segment = sim_segment_factory([node_id], eds_path=str(EDS / file))
    network = canopen.Network(bus_factory())
    network.connect()
    # canopen's own master on the dictionary the device-file reader makes (canopen alone
    # cannot read hand_written.eds: a Latin-1 byte, a key given twice)
    node = BaseNode402(node_id, read_device_file(str(EDS / file)).object_dictionary(node_id))
    for name in ("TIMEOUT_SWITCH_STATE_FINAL", "TIMEOUT_SWITCH_STATE_SINGLE",
                 "TIMEOUT_CHECK_TPDO"):  # a loaded 2-core machine answers late, not wrong
        setattr(node, name, VIRTUAL.stall)
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = VIRTUAL.stall
    try:
        node.nmt.send_command(0x80)  # pre-operational: PDO configuration by SDO
        node.setup_402_state_machine(read_pdos=True)
        assert 0x6040 in node.rpdo_pointers and 0x6041 in node.tpdo_pointers  # via PDOs
        node.nmt.send_command(0x01)  # operational: PDOs
        network.sync.start(0.01)
        node.state = "OPERATION ENABLED"
        assert segment.drives[node_id].state402 == State402.OPERATION_ENABLED
        node.state = "SWITCH ON DISABLED"
        assert segment.drives[node_id].state402 == State402.SWITCH_ON_DISABLED
    finally:
        network.sync.stop()
        network.disconnect()


def test_canopen_reads_every_file_as_the_driver_does():
    for path in sorted(EDS.iterdir()):
        od = read_device_file(str(path)).object_dictionary(5)
        assert cia402.STATUSWORD in od and cia402.CONTROLWORD in od, path.name


def test_a_controller_that_needs_missing_feedback_is_refused_at_load():
    from rocoma_can.cli.demo.config import demo_config
    from rocoma_can.errors import ConfigError
    from rocoma_can.runtime.config import validate
    cfg = demo_config("x", drives=2, rate=100.0, emulated=None)
    for d in cfg["drives"]:
        d["eds"] = str(EDS / "minimal.eds")  # no 0x6077: no torque feedback
        d["modes"] = ["csp"]
        d["feedback"] = ["position"]  # and velocity left out on purpose
    cfg["controllers"][0]["params"]["mode"] = "CSP"
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    text = str(info.value)
    assert "controller 'damp' needs velocity feedback, which drive(s) joint1, joint2 do " \
           "not report" in text
    for d in cfg["drives"]:
        d["feedback"] = ["position", "velocity"]
    for entry in cfg["controllers"]:
        entry["emergency"] = "damp"
    cfg["emergency_controllers"][0] = {"name": "damp", "plugin": "damp"}
    assert validate(cfg).plans["joint1"].drive.feedback == ("position", "velocity")
