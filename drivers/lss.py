"""LSS (CiA 305, layer setting services), the master's side: find nodes that have no node
id yet and give one a node id and a bit rate, through canopen's LssMaster.

A node is addressed by its LSS address, the four values of its identity object (0x1018:
vendor-ID, product code, revision number, serial number), so a node without a node id
(0xFF: unconfigured) can still be told apart from the others. LSS uses two COB-IDs of its
own (0x7E5 master to slaves, 0x7E4 back) and works in any NMT state.

Fastscan finds one unconfigured node in about 130 request/answer turns, each of which
waits for an answer that only comes when the bits asked about match: a missing answer
costs the whole ``timeout``, so the timeout decides how long a fastscan takes (about 64
timeouts per node found, and one for a bus without unconfigured nodes).
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import canopen
from canopen.lss import LssError, LssMaster

from ..errors import LssFailed
from .identity import Identity

#: master -> slaves, slaves -> master
LSS_REQUEST = LssMaster.LSS_TX_COBID
LSS_RESPONSE = LssMaster.LSS_RX_COBID
#: the node id of a node that has none (CiA 305)
UNCONFIGURED = 0xFF
#: CiA 305 bit timing table 0: table index -> bit/s (index 5 is reserved, 9 is automatic)
BIT_TIMING = {0: 1_000_000, 1: 800_000, 2: 500_000, 3: 250_000, 4: 125_000,
              6: 50_000, 7: 20_000, 8: 10_000}
#: how long a fastscan waits for an answer (a slave answers within milliseconds)
TIMEOUT = 0.05
#: most unconfigured nodes one listing looks for (a bound on its time)
MAX_NODES = 32


def bit_timing_index(bitrate: int) -> int:
    """The CiA 305 table index of ``bitrate`` (bit/s); ValueError for one not in it."""
    for index, rate in BIT_TIMING.items():
        if rate == bitrate:
            return index
    raise ValueError(f"bit rate {bitrate} is not in the CiA 305 table "
                     f"({', '.join(str(r) for r in BIT_TIMING.values())})")


@contextmanager
def _answers_within(lss: LssMaster, timeout: float) -> Iterator[None]:
    """canopen's LssMaster with this response timeout (its own: 0.5 s, the class's)."""
    previous, lss.RESPONSE_TIMEOUT = lss.RESPONSE_TIMEOUT, timeout
    try:
        yield
    finally:
        lss.RESPONSE_TIMEOUT = previous


def find_unconfigured(network: canopen.Network, timeout: float = TIMEOUT,
                      limit: int = MAX_NODES) -> list[Identity]:
    """The identity of every node without a node id, by fastscan; each one found stays
    in LSS configuration state (it takes no part in the next fastscan) until all are
    switched back to waiting, which changes nothing on a node that got no new id."""
    lss = network.lss
    found: list[Identity] = []
    with _answers_within(lss, timeout):
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
        try:
            while len(found) < limit:
                ok, address = lss.fast_scan()
                if not ok:
                    break
                found.append(Identity(*address))
        finally:
            lss.send_switch_state_global(LssMaster.WAITING_STATE)
    return found


def assign(network: canopen.Network, node_id: int, address: Identity | None = None, *,
           bitrate: int | None = None, store: bool = False,
           timeout: float = TIMEOUT) -> Identity:
    """Give one node ``node_id`` (and the bit rate ``bitrate``), then switch every node
    back to waiting: a node that had no node id starts with the new one at once, a node
    that had one at its next NMT reset. ``address``: that node's LSS address (all four
    fields); None: the first unconfigured node fastscan finds. ``store``: kept across a
    power cycle (CiA 305 store configuration). Returns the node's address.

    Raises LssFailed when no node answers or the node refuses a value."""
    if not 1 <= node_id <= 127:
        raise ValueError(f"node id must be 1..127, got {node_id}")
    index = bit_timing_index(bitrate) if bitrate is not None else None
    lss = network.lss
    with _answers_within(lss, timeout):
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
        try:
            target = _select(lss, address)
            for what, step in (
                    (f"configure node id {node_id}", lambda: lss.configure_node_id(node_id)),
                    *(((f"configure bit timing {bitrate}",
                        lambda: lss.configure_bit_timing(index)),) if index is not None
                      else ()),
                    *((("store configuration", lss.store_configuration),) if store else ())):
                try:
                    step()
                except LssError as exc:
                    raise LssFailed(f"LSS {what} for {target.describe()}: {exc}") from None
        finally:
            lss.send_switch_state_global(LssMaster.WAITING_STATE)
    return target


def _select(lss: LssMaster, address: Identity | None) -> Identity:
    """Put exactly the one node into LSS configuration state."""
    if address is None:
        ok, found = lss.fast_scan()
        if not ok:
            raise LssFailed("LSS fastscan: no unconfigured node answered")
        return Identity(*found)
    parts = (address.vendor_id, address.product_code, address.revision, address.serial)
    if any(p is None for p in parts):
        raise ValueError(f"an LSS address needs all four identity fields, got "
                         f"{address.describe()}")
    try:
        if lss.send_switch_state_selective(*parts):
            return address
    except LssError:
        pass
    raise LssFailed(f"LSS switch state selective: no node answered at {address.describe()}")

