"""docs/first-robot.md as a test reads it: its sessions parsed and compared by the rules
tests/vcan/test_vcan_first_robot.py runs them with (in the vcan suite: every command is a
SocketCAN one), and the parts that are no command checked here: the wiring commands are
doctor's fixes, the quoted refusal of swapped drives is bring-up's words."""
from __future__ import annotations

import logging

import pytest
from fixtures.budgets import STALL
from fixtures.bus import scan_bus_args
from fixtures.doc_page import blocks, excerpt, matches, steps
from fixtures.init_config import bring_up
from fixtures.paths import ROOT

from rocoma_can.cli.main import main
from rocoma_can.drivers.files.identity import Identity
from rocoma_can.runtime.can_checks import TXQUEUELEN_MIN, setup_command

PAGE = ROOT / "docs" / "first-robot.md"


@pytest.mark.parametrize("shown, printed, same", [
    (["a", "b"], ["a", "b"], True),
    (["a", "b"], ["a", "c"], False),
    (["a"], ["a", "b"], False),                       # a line the page does not show
    (["a", "...", "d"], ["a", "b", "c", "d"], True),
    (["a", "...", "d"], ["a", "d"], True),            # ... may stand for no line
    (["a", "..."], ["a"], True),
    (["x ... z"], ["x any text z"], True),
    (["x ... z"], ["x any text"], False),
    (["a.b (c)"], ["aXb (c)"], False),                # the rest is literal
    (["a  "], ["a"], True),                           # trailing blanks do not count
    (["x  y   ..."], ["x y z"], True),                # a run of blanks is one
    (["x y"], ["xy"], False),
])
def test_a_shown_session_matches_only_what_it_shows(shown, printed, same):
    assert matches(shown, printed) is same


def test_a_yaml_excerpt_is_lines_of_the_file_in_order():
    assert excerpt(["b", "d"], "a\nb\nc\nd\n")
    assert not excerpt(["d", "b"], "a\nb\nc\nd\n")
    assert not excerpt(["b", "e"], "a\nb\nc\nd\n")


def test_the_page_is_a_session_the_vcan_test_can_run():
    """What tests/vcan/test_vcan_first_robot.py relies on: the bench's drives start first,
    in the background; every command is rocoma-can's but the bench's margins, appended to
    the config the page wrote; run is the only other one that does not end by itself, at
    the rate the page says its bench holds."""
    session = steps(PAGE)
    assert session[0].command == "rocoma-can sim --channel vcan0 --nodes 1,2,3"
    assert session[0].background and session[0].section == "This page's bench"
    (margins,) = [s for s in session if not s.command.startswith("rocoma-can ")]
    assert margins.command.startswith("cat >> robot.yaml <<'EOF'\nsupervision: {")
    assert margins.command.endswith("\nEOF") and not margins.shown
    runs = [s for s in session if s.command.startswith("rocoma-can run ")]
    assert [s.command for s in runs] == ["rocoma-can run robot.yaml --rate 25"]
    assert "which three drives hold there" in " ".join(PAGE.read_text().split())
    verbs = [s.command.split()[1] for s in session]
    assert verbs == ["sim", "scan", "init-config", "check-config", "doctor", ">>", "run",
                     "status", "clear", "switch", "status", "home"]
    assert all(s.shown for s in session if s is not margins), \
        "every command shows what it prints"


def test_the_bench_margins_make_a_config_check_config_accepts(tmp_path, capsys):
    """The page's config (its excerpt, a drive of the generic file) with the margins its §6
    appends for the bench, at the bench's rate."""
    import yaml
    (margins,) = [s for s in steps(PAGE) if s.command.startswith("cat >> ")]
    (excerpt_block,) = [b for b in blocks(PAGE) if b.language == "yaml"]
    text = "\n".join(excerpt_block.lines).replace("eds/", f"{ROOT}/eds/")
    text = text.replace("interface: socketcan, channel: can0", "interface: virtual, "
                        "channel: page")
    (tmp_path / "robot.yaml").write_text(text + "\n" + "\n".join(
        margins.command.split("\n")[1:-1]) + "\n")
    config = yaml.safe_load((tmp_path / "robot.yaml").read_text())
    assert config["supervision"]["consumer_factor"] * config["manager"]["heartbeat_ms"] \
        == 10_000  # ms: the drives' consumer of the manager's heartbeat
    assert main(["check-config", str(tmp_path / "robot.yaml")]) == 0, capsys.readouterr()


def test_the_wiring_commands_are_what_doctor_prints_as_fixes():
    (wire,) = [b for b in blocks(PAGE) if b.section == "1. Wire"]
    assert list(wire.lines) == [setup_command("can0", 1_000_000),
                                f"sudo ip link set can0 txqueuelen {TXQUEUELEN_MIN}"]


def test_the_quoted_refusal_of_swapped_drives_is_bring_ups(sim_segment_factory,
                                                           virtual_channel, tmp_path, caplog):
    """§3's quote: the page's bench (the generic drives), nodes 1 and 2 swapped after
    init-config wrote the config."""
    (quote,) = [b for b in blocks(PAGE) if b.section.startswith("3. ") and not b.language
                and not b.lines[0].startswith("$ ")]
    segment = sim_segment_factory([1, 2])
    out = tmp_path / "robot.yaml"
    assert main(["init-config", *scan_bus_args("virtual", virtual_channel, STALL),
                 "--eds-dir", str(ROOT / "eds"), "-o", str(out)]) == 0
    segment.drives[1].swap(Identity(serial=2))
    segment.drives[2].swap(Identity(serial=1))
    with caplog.at_level(logging.ERROR, logger="rocoma_can.drivers.hardware"):
        status = bring_up(out)
    assert [s.phase for s in status] == ["FAILED", "FAILED"]
    said = [r.getMessage() for r in caplog.records if "start-up failed" in r.getMessage()]
    assert quote.lines[0] in said, said
