"""What one CAN frame costs on the wire, in bits at the nominal bit rate: the bus-load check
(runtime/bus_load.py) and the manager node's block-upload pacing (node/server.py) count
with it, and ``fd_length`` says how long a CAN FD frame's data field is on the wire; and a
frame's flags in one byte, as the recording and the in-process link keep them; and
``picker``, which picks a PDO's values for packing (the master's frames_out.py and the
simulated drives' sim/pdo.py)."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from operator import itemgetter
from typing import Any

#: A frame's flags in one byte, as the recording's frame records (record/rings.py, read by
#: record/can_log.py) and the in-process link's datagrams (inproc_link.py) keep them. Each
#: encodes inline, ``is_extended_id | is_remote_frame << 1 | ... | error_state_indicator
#: << 5`` (a function call per frame would cost the loop's thread more than the encoding).
EXTENDED, REMOTE, ERROR, FD, BRS, ESI = 1, 2, 4, 8, 16, 32

#: the data lengths a CAN FD frame's DLC can say beyond 8 bytes (ISO 11898-1)
FD_LENGTHS = (12, 16, 20, 24, 32, 48, 64)
#: the fastest CAN FD data phase a config may give, bit/s (SIC transceivers run 8-10)
MAX_DATA_BITRATE = 15_000_000


def fd_length(data_bytes: int) -> int:
    """The data field a CAN FD frame of ``data_bytes`` takes: up to 8 bytes as given, then
    the next length a DLC can say (9 bytes go out as 12). Receivers get the padded length:
    a PDO codec and the simulated drives pad to it (pdo_layout.py, sim/pdo.py)."""
    if not 0 <= data_bytes <= FD_LENGTHS[-1]:
        raise ValueError(f"a CAN FD frame carries 0..64 data bytes, not {data_bytes}")
    return data_bytes if data_bytes <= 8 else next(n for n in FD_LENGTHS if n >= data_bytes)


def frame_bits(data_bytes: int, worst_case: bool = True,
               data_ratio: float | None = None) -> float:
    """Bits on the wire of an 11-bit CAN frame, 3-bit intermission included, counted at the
    nominal (arbitration) bit rate.

    ``data_ratio`` None: a classic frame, 47 + 8n bits plus stuffing. Otherwise a CAN FD
    frame whose data phase (ESI, DLC, data, stuff count, CRC-17 up to 16 bytes or CRC-21,
    the fixed stuff bits and the CRC delimiter) runs at the data bit rate: ``data_ratio`` =
    nominal / data bit rate (1.0 without bit rate switching). Worst case: one stuff bit per
    four bits where stuffing is dynamic. An FD frame's data is counted at its padded
    length (``fd_length``)."""
    if data_ratio is None:
        bits = 8 * data_bytes + 47
        if worst_case:
            bits += (34 + 8 * data_bytes - 1) // 4
        return bits
    data_bytes = fd_length(data_bytes)
    arbitration = 17  # SOF, 11-bit id, RRS, IDE, FDF, res, BRS
    tail = 12         # ACK slot and delimiter, EOF, intermission
    dynamic = 1 + 4 + 8 * data_bytes  # ESI, DLC, data
    fixed = 4 + (17 if data_bytes <= 16 else 21)  # stuff count with parity, CRC
    data_phase = dynamic + fixed + -(-fixed // 4) + 1  # fixed stuff bits, CRC delimiter
    if worst_case:
        arbitration += (arbitration - 1) // 4
        data_phase += (dynamic - 1) // 4
    return arbitration + tail + data_phase * data_ratio


def picker(keys: Sequence[Any]) -> Callable[[Any], tuple[Any, ...]]:
    """A function giving the entries at ``keys`` of a sequence or a mapping as a tuple, for
    a PDO codec's ``pack_into``: ``itemgetter``, except that one key also gives a tuple and
    none an empty one (cheaper than a comprehension per frame, on the loop's thread)."""
    if len(keys) == 1:
        get = itemgetter(keys[0])
        return lambda values: (get(values),)
    if not keys:
        return lambda values: ()
    return itemgetter(*keys)
