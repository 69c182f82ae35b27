"""The demo's torque-off probes (cli/demo/probe.py) on real in-process buses: they see only
what is sent once armed, every drive's zero controlword on every bus; a bus that does not
open, a loop that stopped first, or an arm after the demo closed them leave nothing open and
say why."""
from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable

import can
import pytest

from rocoma_can.cli.demo.config import demo_config
from rocoma_can.cli.demo.probe import TorqueOffProbes, controlword_carriers
from rocoma_can.cli.demo.walkthrough import _only
from rocoma_can.drivers.link import inproc
from rocoma_can.drivers.link.bus import open_bus
from rocoma_can.runtime.config import RuntimeConfig, validate

DRIVES, BUSES = 4, 2
WAIT = 5.0  # s a reader thread may take to hand a frame over on a busy machine


def _config(interface: str) -> RuntimeConfig:
    return validate(demo_config(f"probe-{uuid.uuid4().hex[:8]}", DRIVES, 100.0, BUSES,
                                interface), source="test")


def _opener(interface: str,
            fail_on: str | None = None) -> Callable[[str, set[int]], can.BusABC]:
    def open_probe(channel: str, cob_ids: set[int]) -> can.BusABC:
        if channel == fail_on:  # a real refusal: python-can's bus with no queue
            return open_bus(interface, channel, rx_queue_size=0)
        return open_bus(interface, channel, receive_own_messages=False,
                        can_filters=_only(cob_ids))
    return open_probe


def _send_torque_off(config: RuntimeConfig, interface: str) -> None:
    """Every drive's controlword RPDO with 0x0000, from a handle of its own per bus."""
    for bus_config in config.buses:
        with open_bus(interface, bus_config.channel) as sender:
            for cob_id, (_, at) in controlword_carriers(config, bus_config.label).items():
                sender.send(can.Message(arbitration_id=cob_id, data=bytes(at + 2),
                                        is_extended_id=False))


def _probe_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("demo-probes")]


@pytest.mark.parametrize("interface", ["inproc", "virtual"])
def test_the_probes_see_only_what_is_sent_once_armed(interface):
    config = _config(interface)
    probes = TorqueOffProbes(config, _opener(interface))
    try:
        _send_torque_off(config, interface)  # the walk-through's RPDOs: nobody listens
        probes.arm()
        assert probes.error is None
        time.sleep(0.2)
        assert probes.seen() == 0
        _send_torque_off(config, interface)  # the loop's stop
        deadline = time.monotonic() + WAIT
        while probes.seen() < DRIVES and time.monotonic() < deadline:
            time.sleep(0.01)
        assert probes.seen() == DRIVES
        assert [len(p.seen) for p in probes.probes] == [DRIVES // BUSES] * BUSES
    finally:
        probes.close()
    assert not _probe_threads()


def test_a_bus_that_does_not_open_is_said_and_leaves_nothing_open():
    config = _config("inproc")
    second = config.buses[1].channel
    probes = TorqueOffProbes(config, _opener("inproc", fail_on=second))
    probes.arm()  # does not raise: the loop's stop comes after it in any case
    assert probes.error is not None and "did not open" in probes.error
    probes.close()
    assert not inproc._channels.get(config.buses[0].channel)
    assert not _probe_threads()


def test_a_loop_that_stopped_first_or_a_closed_probe_opens_nothing():
    config = _config("inproc")
    stopped = TorqueOffProbes(config, _opener("inproc"))
    stopped.arm("duration reached")
    assert stopped.error == "the loop stopped (duration reached) before the probes opened"
    late = TorqueOffProbes(config, _opener("inproc"))
    late.close()  # the demo's end came first (an operator stuck past its join)
    late.arm()
    assert late.error is None
    assert not any(inproc._channels.get(b.channel) for b in config.buses)
    assert not _probe_threads()
