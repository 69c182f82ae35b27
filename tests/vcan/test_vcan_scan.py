"""rocoma_can/cli/scan.py, init_config.py: ``rocoma-can scan`` / ``init-config`` / ``lss`` (and
``run``) on a SocketCAN link that is down or missing: the first mistake on a real robot (the
interface never set up). One line saying so and how to bring it up, exit 2, before anything is
sent."""
from __future__ import annotations

import pytest
from fixtures.console import untimed

from rocoma_can.cli.main import main


@pytest.mark.parametrize("verb", [["scan"], ["init-config", "--eds-dir", "."],
                                  ["lss", "--fastscan", "--set-node-id", "3"]])
def test_a_link_that_is_down_is_one_line_with_the_command_that_brings_it_up(
        vcan_link, capsys, verb):
    vcan_link("vcan0", "down")
    assert main([*verb, "--channel", "vcan0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("rocoma-can: socketcan:vcan0: the link is down: sudo ip link set vcan0 up "
                   "(at the drives' bit rate: rocoma-can doctor checks the link)")


def test_a_missing_link_is_one_line_with_how_to_create_it(capsys):
    """Only rocoma-can's line: not python-can's ERROR log before it."""
    assert main(["scan", "--channel", "vcan7"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("rocoma-can: socketcan:vcan7: no network interface 'vcan7': sudo modprobe "
                   "vcan && sudo ip link add dev vcan7 type vcan && sudo ip link set vcan7 up")


def test_run_on_a_missing_link_is_one_line_with_what_to_check(tmp_path, capsys, caplog):
    """`run` with a channel that is no network interface (a typo, an adapter not plugged
    in): python-can's own ERROR line came first ("Could not access SocketCAN device"), then
    ours with only "[Errno 19] No such device". One line, with where to look."""
    import yaml
    from fixtures.configs import good
    cfg = good()
    cfg["bus"] = {"interface": "socketcan", "channel": "vcan7"}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["run", str(path), "--no-flight", "--duration", "1"]) == 2
    assert untimed(capsys.readouterr().err) == [
        "rocoma-can: error: cannot open CAN bus socketcan:vcan7: [Errno 19] No such device; no "
        "such network interface: `ip link` lists them (an adapter plugged in, its driver "
        "loaded?); rocoma-can doctor CONFIG checks each bus and says how to create or raise "
        "it"]
    assert not [r for r in caplog.records if r.name.startswith("can.")]
