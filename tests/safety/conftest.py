"""Fixtures of the safety matrix (instruments in safety_rig.py)."""
from __future__ import annotations

import pytest
from fixtures.node_rig import Rig as ServiceRig
from safety_rig import NODES, served_rig


@pytest.fixture
def served(virtual_channel, sim_segment_factory, bus_factory, frame_recorder):
    """Simulated drives and the whole served manager, holding (safety_rig.served_rig)."""
    recorder = frame_recorder()
    segment = sim_segment_factory(NODES, channel=virtual_channel)
    yield from served_rig(segment, bus_factory(), bus_factory(), bus_factory(), recorder)


@pytest.fixture
def service(bus_factory):
    """The manager node over a joint plant (tests/node/test_services.py), plus a raw bus of a third
    node: frames read there and nowhere else."""
    rig = ServiceRig(bus_factory, must_clear=False)
    rig.raw = bus_factory()
    yield rig
    rig.close()
