"""``rocoma-can scan`` / ``init-config`` / ``lss`` on a SocketCAN link that is down: the
first mistake on a real robot (the interface never set up). One line saying so and how to
bring it up, exit 2, before anything is sent."""
from __future__ import annotations

import pytest

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
