"""rocoma_can/cli/exit_codes.py, rocoma_can/cli/main.py: the CLI's exit codes a shell script relies
on: 0 ok, 1 refused, 2 usage/config, 3 no answer."""
from __future__ import annotations

import errno
import logging
from pathlib import Path

import pytest
import yaml
from fixtures.configs import good, nobody_answers
from fixtures.console import untimed
from fixtures.node_rig import NODE, Rig
from fixtures.paths import ROOT

from rocoma_can.cli.main import main
from rocoma_can.drivers.link.can_link import socketcan_in_kernel

EXAMPLES = ROOT / "rocoma_can" / "examples"


def test_check_config_ok(capsys):
    assert main(["check-config", str(EXAMPLES / "robot_can0.yaml")]) == 0
    assert "bus load: 12 drives at 250 Hz" in capsys.readouterr().out


def test_check_config_lists_every_problem(tmp_path, capsys):
    cfg = good()
    cfg["rate"] = 0
    cfg["drives"][0]["node_id"] = 300
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["check-config", str(path)]) == 2
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"{path}: rate:") and out[1].startswith(f"{path}: drives[0]:")
    assert out[-1] == "2 problem(s)"


def test_run_with_bad_config_is_usage_error(tmp_path, capsys):
    assert main(["run", str(tmp_path / "missing.yaml")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_run_rate_override_is_checked_against_spin(tmp_path, capsys):
    """``run --rate`` changes the period after the file was checked: a spin_us that fit the
    file's rate but not the new one is a usage error naming both, before any bus opens."""
    cfg = good()
    cfg["bus"] = {"interface": "virtual", "channel": "never-opened"}
    cfg["realtime"] = {"spin_us": 1000}  # fits 100 Hz (10 ms), not 2 kHz (500 µs)
    path = tmp_path / "spin.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["run", str(path), "--rate", "2000"]) == 2
    err = capsys.readouterr().err
    assert "realtime.spin_us:" in err and "(500.0 µs at the rate), got 1000 (with --rate)" \
        in err, err
    for bad in ("nan", "inf", "0", "-5", "20000"):  # checked as the file's rate is
        assert main(["run", str(path), "--rate", bad]) == 2, bad
        err = capsys.readouterr().err
        assert "rate: expected a loop rate in Hz, 0 < rate <= 10000" in err, (bad, err)


def test_client_without_manager_is_no_answer(virtual_channel, capsys):
    assert main(["status", "--interface", "virtual", "--channel", virtual_channel,
                 "--timeout", "0.2"]) == 3
    assert "no answer from manager node 100" in capsys.readouterr().err


@pytest.mark.parametrize("args", [
    ["status", "--timeout", "nan"], ["status", "--timeout", "-1"], ["status", "--timeout", "inf"],
    ["status", "--node", "300"], ["switch", "pd", "--wait", "nan"],
    ["status", "--watch", "--interval", "nan"], ["run", "x.yaml", "--duration", "nan"],
    ["run", "x.yaml", "--flight-seconds", "inf"], ["run", "x.yaml", "--flight-seconds", "1e9"],
    ["home", "j1", "--timeout-homing", "0"],
])
def test_numbers_out_of_range_are_usage_errors(args, capsys):
    """argparse's usage error (exit 2) naming the option: not a traceback, not a wait of
    nan seconds (a busy loop) or a run without end."""
    with pytest.raises(SystemExit) as exited:
        main(args)
    assert exited.value.code == 2
    option = next(a for a in args if a.startswith("--") and a not in ("--watch",))
    assert f"argument {option}" in capsys.readouterr().err


def test_numbers_as_a_shell_writes_them():
    from rocoma_can.cli.args import node_id, seconds_or_zero
    assert [node_id("010"), node_id("0x0A"), node_id("10")] == [10, 10, 10]
    assert seconds_or_zero("0") == 0.0  # switch --wait 0: ask, do not wait (PENDING)


def test_client_commands_against_a_manager(bus_factory, virtual_channel, capsys):
    rig = Rig(bus_factory, must_clear=True)
    opts = ["--interface", "virtual", "--channel", virtual_channel, "--node", str(NODE)]
    try:
        assert main(["switch", "pd", *opts]) == 1          # latched: refused, and why
        out, err = capsys.readouterr()
        assert out.strip() == "ERROR" and "switch refused: emergency stop not cleared" in err
        assert main(["clear", *opts]) == 0
        assert main(["switch", "pd", *opts]) == 0
        assert capsys.readouterr().out.strip().splitlines()[-1] == "SWITCHED"
        assert main(["switch", "nope", *opts]) == 1
        assert capsys.readouterr().out.strip() == "NOT_FOUND"  # on stdout, as documented
        # UTF-8 names, numbers no U8 index holds, a byte that is no UTF-8 (the shell's
        # $'\xff': Python's argv holds it as a lone surrogate; a UnicodeEncodeError
        # traceback as it was sent)
        for odd in ("é", "300", "\u00b2", "0", "\udcff"):
            assert main(["switch", odd, *opts]) == 1, odd
            assert capsys.readouterr().out.strip() == "NOT_FOUND", odd
        assert main(["switch", "pd\udce9", *opts]) == 1
        assert "no controller 'pd\\udce9', did you mean 'pd'?" in capsys.readouterr().err
        assert main(["list", *opts]) == 0
        assert capsys.readouterr().out.splitlines() == ["1 pd", "2 trajectory"]
        assert main(["estop", *opts]) == 0
        assert rig.wait_state(1)
        assert main(["status", *opts]) == 0
        out = capsys.readouterr().out
        assert "state: EMERGENCY" in out and "active: damp" in out and "latched: True" in out
        assert main(["failproof", *opts]) == 0 and rig.wait_state(0)
        assert main(["recover", *opts]) == 0 and rig.recovered == 1
    finally:
        rig.close()


def test_a_stop_sends_first_and_then_names_what_it_ignored(bus_factory, virtual_channel,
                                                          capsys):
    """A stop verb acts whatever else the line carries (rocoma_can/stop_surfaces.py: CLI):
    the stop is sent, then one line names the words it did not take, escaped and cut."""
    rig = Rig(bus_factory, must_clear=False)
    opts = ["--interface", "virtual", "--channel", virtual_channel, "--node", str(NODE)]
    try:
        assert main(["clear", *opts]) == 0
        assert main(["switch", "pd", *opts]) == 0
        capsys.readouterr()
        invalid = b"\xff\xfe".decode("utf-8", "surrogateescape")
        assert main(["estop", "now", "--force", invalid, "y" * 500, *opts]) == 0
        assert rig.wait_state(1)
        out, err = capsys.readouterr()
        assert out.strip() == "e-stop requested"
        assert err.strip() == ("rocoma-can: estop: ignored (a stop takes nothing but where to "
                               "send it): 'now', '--force', '\\udcff\\udcfe', '" + "y" * 40
                               + "'... (500 characters)")
        assert main(["failproof", *[f"w{k}" for k in range(9)], *opts]) == 0
        assert rig.wait_state(0)
        assert capsys.readouterr().err.strip().endswith("'w3', 'w4' and 4 more")
    finally:
        rig.close()


@pytest.mark.parametrize("args", [["switch", "pd", "now"], ["clear", "--force"],
                                  ["status", "extra"], ["run", "x.yaml", "--bogus"]])
def test_verbs_other_than_the_stops_still_refuse_words_they_do_not_take(args, capsys):
    with pytest.raises(SystemExit) as exited:
        main(args)
    assert exited.value.code == 2
    assert f"unrecognized arguments: {args[-1]}" in capsys.readouterr().err


def _write(tmp_path: Path, cfg: dict, name: str = "robot.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_check_config_names_a_parameters_path_and_type(tmp_path, capsys):
    """`kp: high` is the parameter's path and what it must be, not a comparison's
    TypeError from inside the constructor."""
    cfg = good()
    cfg["controllers"][0]["params"] = {"kp": "high"}
    cfg["controllers"].append({"name": "mine", "plugin": "fixtures.plugin_samples:Gains",
                               "params": {"kp": "high"}})  # compares kp > 0 unchecked
    path = _write(tmp_path, cfg)
    assert main(["check-config", str(path)]) == 2
    assert capsys.readouterr().out.splitlines() == [
        f"{path}: controllers[0].params.kp: expected a number, got 'high'", "1 problem(s)"]
    cfg["controllers"][0]["params"] = {}
    path = _write(tmp_path, cfg)
    assert main(["check-config", str(path)]) == 2
    assert capsys.readouterr().out.splitlines() == [
        f"{path}: controllers[1].params.kp: expected a number (float), got 'high'",
        "1 problem(s)"]


def test_check_config_misspelt_key_is_one_problem(tmp_path, capsys):
    cfg = good()
    cfg["drives"][0]["mode"] = ["csp"]
    cfg["controlers"] = cfg.pop("controllers")
    path = _write(tmp_path, cfg)
    assert main(["check-config", str(path)]) == 2
    out = capsys.readouterr().out.splitlines()
    assert [line.split(" (known: ")[0] for line in out] == [
        f"{path}: controlers: unknown key, did you mean 'controllers'?",
        f"{path}: drives[0].mode: unknown key, did you mean 'modes'?",
        "2 problem(s)"]


def test_check_config_says_where_a_limit_written_on_the_drive_belongs(tmp_path, capsys):
    """`following_error_cycles: 4000` (issue 53's words) written on the drive, not in its
    limits: "unknown key" and a list of 30 keys, none of them it."""
    cfg = good()
    cfg["drives"][0]["following_error_cycles"] = 4000
    path = _write(tmp_path, cfg)
    assert main(["check-config", str(path)]) == 2
    assert capsys.readouterr().out.splitlines()[0] == (
        f"{path}: drives[0].following_error_cycles: unknown key here, it goes in limits "
        "(limits: {following_error_cycles: 4000})")


def test_check_config_of_a_valid_file_warns_about_nothing(tmp_path, capsys, caplog):
    """The unused emergency controller is a note on stdout, once; nothing is logged."""
    cfg = good()
    cfg["controllers"][0].pop("emergency")
    path = _write(tmp_path, cfg)
    with caplog.at_level(logging.INFO):
        assert main(["check-config", str(path)]) == 0
    out, err = capsys.readouterr()
    assert out.splitlines()[:2] == [
        f"{path}: ok: 2 drives on socketcan:vcan0 at 100 Hz, manager node 100, e-stop COB-ID "
        "0x0A0",
        "note: emergency_controllers: emergency controller 'damp' is not used by any "
        "controller"]
    assert err == "" and [r.getMessage() for r in caplog.records] == []


def test_run_without_socketcan_says_what_to_do(tmp_path, capsys, monkeypatch):
    """A kernel without AF_CAN (this project's CI, containers, WSL): the errno, then what
    to do instead, on one line."""
    if socketcan_in_kernel():  # the same errno as such a kernel gives, from python-can
        import can

        def no_af_can(*args, **kwargs):
            raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
        monkeypatch.setattr(can, "Bus", no_af_can)
    cfg = good()
    cfg["bus"] = {"interface": "socketcan", "channel": "can0"}
    path = _write(tmp_path, cfg)
    assert main(["run", str(path), "--no-flight", "--duration", "1"]) == 2
    assert untimed(capsys.readouterr().err) == [
        "rocoma-can: error: cannot open CAN bus socketcan:can0: [Errno 97] Address family not "
        "supported by protocol; this kernel has no SocketCAN (AF_CAN): on vcan, from a "
        "checkout, tools/vcan-run -- rocoma-can run CONFIG with channel: vcan0; without a "
        "kernel bus, rocoma-can demo, or interface: virtual in CONFIG"]


@pytest.mark.parametrize("verb", [["status"], ["estop"], ["record", "x.log"]])
def test_a_verb_reaching_the_bus_without_socketcan_says_where_it_can(verb, tmp_path, capsys,
                                                                      monkeypatch):
    """As run does: the errno, then what to do, on one line (status said the bare errno)."""
    if socketcan_in_kernel():
        import can

        def no_af_can(*args, **kwargs):
            raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
        monkeypatch.setattr(can, "Bus", no_af_can)
    monkeypatch.chdir(tmp_path)
    assert main([*verb, "--channel", "can0"]) == 2
    assert capsys.readouterr().err == (
        "rocoma-can: cannot open CAN bus socketcan:can0: [Errno 97] Address family not "
        "supported by protocol; this kernel has no SocketCAN (AF_CAN): run it where the "
        "manager's bus is: the robot's computer, or on vcan, from a checkout, inside "
        "tools/vcan-run beside the manager\n")


def test_a_timed_run_with_no_drive_answering_says_so_and_fails(tmp_path, capfd, caplog):
    """No drive on the bus: said once, for the bus, with what to check, and a run whose
    bring-up never finished exits 1, not "stopped (duration reached)" and 0; the end says
    why without repeating it."""
    path = nobody_answers(tmp_path)
    assert main(["run", str(path), "--duration", "3", "--no-flight"]) == 1
    channel = f"nobody-{tmp_path.name}"
    assert untimed(capfd.readouterr().err) == [
        f"rocoma-can: error: no drive answers on {channel}: j1 (node 1) did not answer (SDO "
        "0x1000, 3 x 0.05 s); check that the drives have power, the bit rate (every node's "
        "and the interface's must be the same), the cable and its termination (120 ohm at "
        "both ends of the bus), and the node ids (rocoma-can scan lists what answers)",
        "rocoma-can: error: bring-up did not finish: 1 of 1 drives failed (said above)"]
    # canopen's own ERROR line per timed-out try ("Transfer aborted by client with code
    # 0x05040000") is not the operator's: the line above says it once, with what to check
    assert not [r for r in caplog.records if r.name == "canopen.sdo.client"]


@pytest.mark.parametrize("args", [
    ["status"], ["list"], ["estop"], ["failproof"], ["clear"], ["recover"], ["switch", "pd"],
    ["home", "j1"], ["scan"], ["record", "never.log", "--duration", "0.1"],
    ["sim", "--nodes", "1"],
])
def test_an_interface_python_can_does_not_know_is_one_line(args, tmp_path, capsys,
                                                           monkeypatch):
    """A typo in --interface (socketcna) is a usage error naming it, with the nearest
    interface python-can knows: not NotImplementedError's traceback, exit 1."""
    monkeypatch.chdir(tmp_path)
    assert main([*args, "--interface", "socketcna", "--channel", "x"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "\n" not in err.strip(), err
    assert err.startswith("rocoma-can") and "'socketcna' is no interface python-can knows" \
        in err, err
    assert "did you mean 'socketcan'?" in err, err
    assert not (tmp_path / "never.log").exists()


def test_a_config_whose_interface_python_can_does_not_know_is_refused(tmp_path, capsys):
    """check-config said ok to `interface: socketcna`; run and doctor then ended in
    NotImplementedError's traceback."""
    cfg = good()
    cfg["bus"]["interface"] = "socketcna"
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(cfg))
    for verb in (["check-config"], ["run"], ["doctor"], ["status", "-c"]):
        assert main([*verb, str(path)]) == 2, verb
        out = capsys.readouterr()
        assert "Traceback" not in out.err
        assert f"{path}: bus.interface: 'socketcna' is no interface python-can knows, " \
               "did you mean 'socketcan'?" in out.out + out.err, (verb, out)


def test_check_config_says_an_e_stop_frame_turned_off_as_off(tmp_path, capsys):
    """`estop_cob_id: 0` turns the e-stop frame off: "e-stop COB-ID 0x000" read as a frame
    on identifier 0 (NMT's)."""
    cfg = good()
    cfg["manager"]["estop_cob_id"] = 0
    cfg["bus"] = {"interface": "virtual", "channel": "never-opened"}
    path = tmp_path / "off.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["check-config", str(path)]) == 0
    assert capsys.readouterr().out.splitlines()[0].endswith(
        "manager node 100, no e-stop frame (manager.estop_cob_id: 0)")


@pytest.mark.parametrize("verb", [["status"], ["list"], ["switch", "pd"], ["estop"],
                                  ["clear"], ["home", "j1"]])
def test_a_node_that_is_no_manager_is_said_as_such(verb, virtual_channel, capsys):
    """--node pointing at a drive (the wrong --node, which docs/cli.md answers with exit 3):
    its SDO server aborts "object does not exist" (0x06020000), and each verb said "read
    0x2140: refused by the manager (SDO abort 0x06020000: see CiA 301)", exit 1."""
    from rocoma_can.drivers.sim.segment import SimulatedSegment
    segment = SimulatedSegment.open(virtual_channel, "virtual", [1]).start()
    try:
        assert main([*verb, "--interface", "virtual", "--channel", virtual_channel,
                     "--node", "1", "--timeout", "0.3"]) == 3
    finally:
        segment.stop()
    err = capsys.readouterr().err
    assert "rocoma-can: node 1 is no rocoma-can manager (or an older one): it has no object " \
        "0x21" in err, err
    assert "refused by the manager" not in err and err.count("\n") == 1, err
