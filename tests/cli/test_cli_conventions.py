"""rocoma_can/cli/main.py, rocoma_can/cli/args.py: the conventions a command line is expected to
keep (docs/cli.md): ``-v`` before or after the verb, ``--version``, a near name offered for an
unknown verb or controller, a refusal pointing to what lifts it, plain text in --help, one spelling
of each NMT state, one unit for the loop's timing, a channel that is a number (Kvaser, IXXAT,
Vector) read as the text it is, and the operator verbs reaching the manager a config names (``-c
robot.yaml``)."""
from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import pytest
import yaml
from fixtures.budgets import STALL
from fixtures.bus import scan_bus_args
from fixtures.configs import good
from fixtures.node_rig import NODE, Rig
from fixtures.paths import TESTS

from rocoma_can import __version__
from rocoma_can.cli.exit_codes import FAILED, NO_ANSWER, OK
from rocoma_can.cli.main import build_parser, main
from rocoma_can.drivers.commission.scan import nmt_state_name
from rocoma_can.drivers.protocol import cia301
from rocoma_can.runtime.config import load, load_reach
from rocoma_can.runtime.loop import TimingSummary

EDS = TESTS / "fixtures" / "eds"


# --- -v, --version, unknown verbs, --help ----------------------------------------------------
def _no_manager(channel: str) -> list[str]:
    return ["status", "--interface", "virtual", "--channel", channel, "--timeout", "0.05"]


@pytest.mark.parametrize("where", ["before", "after"])
def test_verbose_works_before_and_after_the_verb(where, virtual_channel, capsys):
    """-vv shows canopen's own line for each SDO try that timed out (said once otherwise):
    the same whether -vv comes before the verb or after it."""
    verb = _no_manager(virtual_channel)
    args = ["-vv", *verb] if where == "before" else [*verb, "-vv"]
    assert main(args) == NO_ANSWER
    err = capsys.readouterr().err
    assert "rocoma-can: error: canopen.sdo.client: Transfer aborted by client" in err, err
    assert main(verb) == NO_ANSWER
    assert "Transfer aborted by client" not in capsys.readouterr().err


def test_verbose_counts_on_both_sides():
    args = build_parser().parse_args(["-v", "status", "-v"])
    assert args.verbose + args.verbose_after == 2


def test_version_prints_the_distributions_version(capsys):
    with pytest.raises(SystemExit) as exited:
        main(["--version"])
    assert exited.value.code == OK
    assert capsys.readouterr().out == f"rocoma-can {__version__}\n"


@pytest.mark.parametrize(("typed", "meant"), [("stauts", "status"), ("swich", "switch"),
                                              ("chek-config", "check-config")])
def test_an_unknown_verb_gets_the_nearest_as_a_hint(typed, meant, capsys):
    with pytest.raises(SystemExit) as exited:
        main([typed])
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"rocoma-can: error: unknown command {typed!r}, did you mean {meant!r}? (rocoma-can "
        "--help lists them)")


def _parsers(parser: argparse.ArgumentParser, path: str):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, f"{path} {name}")


def test_every_help_is_plain_text():
    """The docstrings and help strings shared with the docs mark code with backticks:
    --help shows none (``rocoma-can sim``'s said ````rocoma-can sim````)."""
    found = [path for path, parser in _parsers(build_parser(), "rocoma-can")
             if "`" in parser.format_help()]
    assert found == []
    assert len(list(_parsers(build_parser(), "rocoma-can"))) > 20  # every verb was seen


# --- the operator verbs -----------------------------------------------------------------------
@pytest.fixture
def manager(bus_factory, request):
    rig = Rig(bus_factory, must_clear=getattr(request, "param", True))
    yield rig
    rig.close()


def _opts(channel: str) -> list[str]:
    return ["--interface", "virtual", "--channel", channel, "--node", str(NODE)]


def test_an_unknown_controller_gets_the_nearest_as_a_hint(manager, virtual_channel, capsys):
    assert main(["switch", "trajectry", *_opts(virtual_channel)]) == FAILED
    out, err = capsys.readouterr()
    assert out == "NOT_FOUND\n"
    assert err == ("rocoma-can: no controller 'trajectry', did you mean 'trajectory'? "
                   "(rocoma-can list names them)\n")
    assert main(["switch", "hold_pos", *_opts(virtual_channel)]) == FAILED  # none near
    assert capsys.readouterr().err == ("rocoma-can: no controller 'hold_pos' (rocoma-can "
                                       "list names them)\n")


def test_a_latched_refusal_points_to_clear(manager, virtual_channel, capsys):
    assert main(["switch", "pd", *_opts(virtual_channel)]) == FAILED
    assert capsys.readouterr().err == ("rocoma-can: switch refused: emergency stop not "
                                       "cleared (rocoma-can clear clears it)\n")
    assert main(["clear", *_opts(virtual_channel)]) == OK
    assert main(["switch", "pd", *_opts(virtual_channel)]) == OK


def _config_of(tmp_path: Path, channel: object, node: int = NODE, **extra: object) -> Path:
    cfg = good()
    cfg["bus"] = {"interface": "virtual", "channel": channel}
    cfg["manager"]["node_id"] = node
    cfg.update(extra)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.parametrize(("verb", "code"), [
    (["status"], OK), (["status", "--json"], OK), (["list"], OK), (["switch", "pd"], FAILED),
    (["clear"], OK), (["estop"], OK), (["failproof"], OK), (["recover"], OK),
    (["home", "j1"], FAILED)], ids=lambda v: " ".join(v) if isinstance(v, list) else str(v))
def test_every_operator_verb_reaches_the_manager_a_config_names(verb, code, manager,
                                                                virtual_channel, tmp_path,
                                                                capsys):
    """``-c robot.yaml``: its bus's interface and channel, its manager's node id. (A
    latched switch is refused, and this rig has no drives to home: both answers of the
    manager, not a manager nobody reached, exit 3.)"""
    path = _config_of(tmp_path, virtual_channel)
    assert main([*verb, "-c", str(path), "--timeout", "1"]) == code, capsys.readouterr()
    assert "no answer" not in capsys.readouterr().err


def test_an_option_overrides_the_config(manager, virtual_channel, tmp_path, capsys):
    path = _config_of(tmp_path, virtual_channel)
    assert main(["status", "-c", str(path), "--node", "7", "--timeout", "0.05"]) == NO_ANSWER
    assert "no answer from manager node 7" in capsys.readouterr().err
    elsewhere = _config_of(tmp_path, "nobody-here")
    assert main(["list", "-c", str(elsewhere), "--channel", virtual_channel]) == OK
    assert capsys.readouterr().out == "1 pd\n2 trajectory\n"


def test_a_config_the_operator_verbs_cannot_read_is_a_usage_error(tmp_path, capsys):
    path = tmp_path / "robot.yaml"
    path.write_text("manager: {node_id: 300}\n")
    assert main(["status", "-c", str(path)]) == 2
    assert capsys.readouterr().err == (f"rocoma-can: {path}: manager.node_id: expected an "
                                       "integer 1..127, got 300\n")


def test_the_operator_verbs_read_only_what_reaches_the_manager(tmp_path):
    """An operator's machine may lack the drives' files and the controllers' plug-ins:
    the rest of the config is not read."""
    path = _config_of(tmp_path, "arm", node=42, zenoh={"prefix": "robots/arm"})
    cfg = yaml.safe_load(path.read_text())
    cfg["drives"][0]["eds"] = "missing.eds"
    cfg["controllers"][0]["plugin"] = "not_installed_here"
    path.write_text(yaml.safe_dump(cfg))
    reach = load_reach(path)
    assert (reach.interface, reach.channel, reach.node_id, reach.zenoh_prefix) == (
        "virtual", "arm", 42, "robots/arm")


# --- a numeric channel ------------------------------------------------------------------------
def test_a_numeric_channel_is_read_as_its_text(tmp_path):
    """Kvaser, IXXAT and Vector number their channels: ``channel: 29536`` or ``channel: 0``
    unquoted is an int to YAML, and a channel is text wherever it is read."""
    for written, read in ((29536, "29536"), (0, "0")):
        path = _config_of(tmp_path, written)
        assert load(path).bus.channel == read
        assert load_reach(path).channel == read
    path = _config_of(tmp_path, -1)
    with pytest.raises(Exception, match="bus.channel: expected a non-empty string, got -1"):
        load(path)


def test_init_config_writes_a_numeric_channel_it_can_read_back(sim_segment_factory,
                                                              tmp_path):
    channel = "29536"  # a virtual bus of that name stands for a Kvaser's channel
    sim_segment_factory([1], channel=channel, eds_path=str(EDS / "vendor_a.eds"))
    folder = tmp_path / "eds"
    folder.mkdir()
    shutil.copy(EDS / "vendor_a.eds", folder)
    out = tmp_path / "robot.yaml"
    assert main(["init-config", *scan_bus_args("virtual", channel, STALL), "--eds-dir",
                 str(folder), "-o", str(out)]) == OK
    assert "channel: '29536'" in out.read_text()
    assert load(out).bus.channel == channel
    assert main(["check-config", str(out)]) == OK


# --- one spelling, one unit -------------------------------------------------------------------
@pytest.mark.parametrize("state", list(cia301.NmtState), ids=lambda s: s.name)
def test_every_nmt_state_is_spelled_as_cia_301_writes_it(state):
    """PRE-OPERATIONAL, as canopen and CiA 301 write it, in status, scan, supervision and
    the simulator alike (status said PRE_OPERATIONAL, scan PRE-OPERATIONAL)."""
    name = cia301.nmt_name(state)
    assert "_" not in name and name.replace("-", "_") == state.name
    if state != cia301.NmtState.BOOT_UP:  # (a scan says what a boot-up leaves)
        assert nmt_state_name(state) == name


def test_run_says_its_timing_in_ms_as_status_does():
    from rocoma_can.cli.status_watch import cycle_text
    summary = TimingSummary(1000, 2, 1, 0.001, 0.00121, 0.00041, 0.00009, 0.00031)
    assert summary.line() == ("cycles 1000, overruns 2 (1 waiting), period mean 1.000 ms max "
                              "1.210 ms, jitter p99 0.090 ms max 0.410 ms, work max 0.310 ms")
    status = {"cycles": 1000, "rate": 1000.0, "overruns": 2, "overruns_waiting": 1,
              "period_mean_ms": 1.0, "period_max_ms": 1.21, "jitter_p99_ms": 0.09,
              "work_max_ms": 0.31}
    assert cycle_text(status) == ("1000 cycles at 1000 Hz, overruns 2 (1 waiting), period "
                                  "mean 1.000 ms max 1.210 ms, jitter p99 0.090 ms, work max "
                                  "0.310 ms")
    assert TimingSummary(0, 0, 0, *[float("nan")] * 5).line() == "no cycle ran"


@pytest.mark.parametrize(("words", "meant"), [
    (["status", "--channle", "can0"], "--channel"),
    (["switch", "pd", "--wiat", "2"], "--wait"),
    (["run", "robot.yaml", "--duraton=5"], "--duration"),
    (["scan", "--channel", "can0", "--jsno"], "--json")])
def test_an_unknown_option_gets_the_nearest_of_its_verb_as_a_hint(words, meant, capsys):
    """As an unknown verb does: argparse (before Python 3.14) names no option for a typo."""
    with pytest.raises(SystemExit) as exited:
        main(words)
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].endswith(
        f", did you mean {meant!r}?"), words


@pytest.mark.parametrize("verb", [["doctor"], ["status"], ["estop"], ["scan"],
                                  ["record", "x.log"], ["sim"], ["lss", "--fastscan"]])
def test_an_empty_channel_is_a_usage_error_not_a_default(verb, capsys):
    """``--channel "$CH"`` with CH unset: doctor checked every link and said "nothing blocks
    it", the others took their default link; now a usage error naming the option."""
    with pytest.raises(SystemExit) as exited:
        main([*verb, "--channel", ""])
    assert exited.value.code == 2
    assert "argument --channel: expected a CAN channel" in capsys.readouterr().err
