"""Rings in memory shared with the recording's writer process: how the loop hands over.

The loop's process only copies: each cycle's signal row (trace.SignalTrace) and each frame
its buses carried (``FrameRing``, received and sent) go into rings allocated once in one
anonymous shared file (``memfd``). The writer process (writer.py) maps the same file and
does everything slow there, on its own interpreter: JSON, MCAP, candump text, the disk.

A ring is a header (the number of records written so far, a u64 the producer stores after
each record) and ``capacity`` fixed-size records. One producer per ring (the loop for rows
and sent frames, the bus's reader for received frames: BusReader hands a bus's frames over
under one lock), any number of readers, no lock: a reader copies what it has not seen, then
reads the count again and drops what the producer overwrote meanwhile (``RingReader.read``).
On x86-64 and ARM64 the count's store is not seen before the record's (release order on
x86; CPython's calls between them order it on ARM in practice), and a torn record can only
be one overwritten during the copy, which the second count read drops, or the one in the
slot the producer writes before it stores the count, which is never read: a ring of
``capacity`` records is read as its last ``capacity - 1``.
"""
from __future__ import annotations

import mmap
import os
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from ..drivers.link.frame_io import MAX_FRAME_AGE
from .can_log import SENT, RecordingError

#: bytes before each ring's records: its count, on a cache line of its own
HEADER = 64
_COUNT = struct.Struct("<Q")



def frame_dtype(fd: bool) -> np.dtype[Any]:
    """One frame record: wall-clock stamp, COB-ID, flags, DLC (payload bytes), payload."""
    return np.dtype([("t", "<f8"), ("id", "<u4"), ("flags", "u1"), ("dlc", "u1"),
                     ("pad", "V2"), ("data", "u1", 64 if fd else 8)])


@dataclass(frozen=True)
class RingSpec:
    """Where a ring lies in the shared file, and its records: ``width`` float64 numbers (a
    signal row) or a frame record (``width`` 0; ``fd``: 64-byte payloads). JSON-able: the
    writer process is told the layout as plain numbers."""
    name: str
    offset: int
    capacity: int
    width: int = 0
    fd: bool = False

    @property
    def dtype(self) -> np.dtype[Any]:
        return np.dtype(("<f8", self.width)) if self.width else frame_dtype(self.fd)

    @property
    def size(self) -> int:
        return HEADER + self.capacity * self.dtype.itemsize


def layout(rings: list[tuple[str, int, int, bool]]) -> list[RingSpec]:
    """(name, capacity, width, fd) per ring, laid out one after another, page-aligned."""
    specs, offset = [], 0
    for name, capacity, width, fd in rings:
        spec = RingSpec(name, offset, capacity, width, fd)
        specs.append(spec)
        offset += -(-spec.size // mmap.PAGESIZE) * mmap.PAGESIZE
    return specs


class SharedFile:
    """The anonymous shared file every ring lies in (``fd`` is handed to the writer process,
    which maps it too; the memory is freed when the last process closes it, so a killed
    process leaves nothing behind).

    Its memory is taken whole at start-up and mapped with every page present: a page first
    touched mid-run would cost the cycle a page fault, and one the machine cannot give any
    more would kill the loop's process (SIGBUS) mid-motion. A size over MEMORY_SHARE of
    the memory available is refused at once, saying how much it needs (RecordingError)."""

    def __init__(self, size: int, fd: int | None = None) -> None:
        self.size = max(size, mmap.PAGESIZE)
        if fd is None:
            _check_memory(self.size)
        self.fd = os.memfd_create("rocoma-can-record", 0) if fd is None else fd
        try:
            if fd is None:
                os.ftruncate(self.fd, self.size)
                try:
                    os.posix_fallocate(self.fd, 0, self.size)
                except OSError as exc:
                    raise RecordingError(f"cannot take {self.size / 1e6:.0f} MB of memory "
                                         f"for the recording's rings: {exc.strerror}") from exc
            self.map = mmap.mmap(self.fd, self.size,
                                 flags=mmap.MAP_SHARED | mmap.MAP_POPULATE)
        except BaseException:
            os.close(self.fd)
            raise

    def array(self, spec: RingSpec) -> np.ndarray:
        """The ring's records as an array over the shared memory (no copy)."""
        return np.frombuffer(self.map, spec.dtype, spec.capacity, spec.offset + HEADER)

    def count(self, spec: RingSpec) -> int:
        return int(_COUNT.unpack_from(self.map, spec.offset)[0])

    def publish(self, spec: RingSpec, count: int) -> None:
        _COUNT.pack_into(self.map, spec.offset, count)

    def counter(self, spec: RingSpec) -> memoryview:
        """The ring's count as a one-item u64 view (a store costs less than a pack)."""
        return memoryview(self.map)[spec.offset:spec.offset + 8].cast("Q")

    def close(self) -> None:
        try:
            self.map.close()
        except BufferError:  # an array or view still looks at it: freed with the last
            pass
        os.close(self.fd)


#: the share of the memory available the rings may take at most
MEMORY_SHARE = 0.5


def _check_memory(size: int) -> None:
    available = memory_available()
    if available is not None and size > MEMORY_SHARE * available:
        raise RecordingError(
            f"the recording's rings need {size / 1e6:.0f} MB of memory, and "
            f"{available / 1e6:.0f} MB are available (they may take half): they keep 10 s, "
            "or the flight recorder's --flight-seconds, of every signal and frame, so a "
            "shorter window (or fewer buses, a lower rate) needs less")


def memory_available() -> int | None:
    """Bytes this process can still take without swapping or being killed: the kernel's
    MemAvailable, or less where its cgroup (v2: a container, a systemd unit's MemoryMax)
    allows less. None if neither says."""
    found = []
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    room = _cgroup_room()
    if room is not None:
        found.append(room)
    return min(found) if found else None


def _cgroup_room() -> int | None:
    """What this process's memory cgroup and those above it still allow (the limit less
    the usage, the least of them; cgroup v2's memory.max, v1's memory.limit_in_bytes);
    None where no limit is set."""
    try:
        with open("/proc/self/cgroup") as cgroups:
            lines = [line.strip().split(":", 2) for line in cgroups]
    except OSError:
        return None
    rooms = []
    for fields in lines:
        if len(fields) != 3:
            continue
        _, controllers, path = fields
        if controllers == "":
            root, files = Path("/sys/fs/cgroup"), ("memory.max", "memory.current")
        elif "memory" in controllers.split(","):
            root = Path("/sys/fs/cgroup/memory")
            files = ("memory.limit_in_bytes", "memory.usage_in_bytes")
        else:
            continue
        folder = root / path.lstrip("/")
        while folder.is_relative_to(root):
            try:
                limit = (folder / files[0]).read_text().strip()
                if limit != "max" and int(limit) < 1 << 60:  # v1 says "none" as ~2**63
                    rooms.append(int(limit) - int((folder / files[1]).read_text()))
            except (OSError, ValueError):
                pass
            if folder == root:
                break
            folder = folder.parent
    return min(rooms) if rooms else None


class FrameRing(can.Listener):
    """One bus's frames in one direction, into the shared file: received (a ``lock_free``
    listener on the hardware's own reader: the frames it reads anyway, no second socket)
    or sent (``sent``, called by BusPort after each frame it sent). No allocation (its cost
    a frame: benchmarks/README.md, "Figures behind constants")."""

    #: BusReader.drain_now may call it on the loop's thread: it takes no lock
    lock_free = True

    def __init__(self, shared: SharedFile, spec: RingSpec, sent: bool) -> None:
        self.spec = spec
        self._map = shared.map
        self._record = struct.Struct(f"<dIBB2x{64 if spec.fd else 8}s").pack_into
        self._base, self._size = spec.offset + HEADER, spec.dtype.itemsize
        self._capacity, self._fd = spec.capacity, spec.fd
        self._published = shared.counter(spec)
        self._sent = SENT if sent else 0
        self.count = 0

    def on_message_received(self, msg: can.Message) -> None:
        """A received frame with its arrival stamp, or "now" where it has none that is
        plausible: some interfaces count from the adapter's power-on (a frame recorded 55
        years ago: out of every flight record, first in the candump log); the hardware
        takes such frames as arrived now too (frame_io.to_monotonic)."""
        stamp, now = msg.timestamp, time.time()
        self.put(msg, stamp if now - MAX_FRAME_AGE < stamp <= now else now)

    def put(self, msg: can.Message, stamp: float) -> None:
        """``msg`` with ``stamp`` (time.time()): a frame sent here has no stamp of its own
        (the cycle's frames are allocated once and sent again and again)."""
        n = self.count
        flags = self._sent | msg.is_extended_id | msg.is_remote_frame << 1 \
            | msg.is_error_frame << 2
        if self._fd:
            flags |= msg.is_fd << 3 | msg.bitrate_switch << 4 | msg.error_state_indicator << 5
        self._record(self._map, self._base + n % self._capacity * self._size, stamp,
                     msg.arbitration_id, flags, msg.dlc, msg.data)
        self.count = n = n + 1
        self._published[0] = n

    def on_error(self, exc: Exception) -> None:  # the bus's problem, reported by its reader
        pass


#: frame records ``frame_chunks`` converts at once (a short step of the writer's, their
#: candump lines too: benchmarks/README.md, "Figures behind constants")
CHUNK = 128
#: a frame as a writer takes it: (stamp, COB-ID, flags, payload in upper-case hex)
Fields = tuple[float, int, int, str]


def frame_fields(records: np.ndarray) -> list[Fields]:
    """Frame records as (stamp, COB-ID, flags, payload in upper-case hex), converted in
    whole arrays (an order of magnitude faster than a frame's fields one by one)."""
    if not len(records):
        return []
    size = records.dtype["data"].shape[0]
    width = size * 2
    hexes = records["data"].tobytes().hex().upper()
    # a frame longer than a record (an FD frame an in-process bus handed a classic bus's
    # reader) keeps what the record holds
    return [(t, cob, flags, hexes[k * width:k * width + 2 * dlc])
            for k, (t, cob, flags, dlc) in enumerate(zip(
                records["t"].tolist(), records["id"].tolist(), records["flags"].tolist(),
                np.minimum(records["dlc"], size).tolist()))]


def frame_chunks(records: np.ndarray) -> Iterator[list[Fields]]:
    """``frame_fields`` of ``records``, ``CHUNK`` at a time: a writer paces between
    (pacing.py), and a flight record's 10 s of frames are not one 50 ms conversion."""
    for first in range(0, len(records), CHUNK):
        yield frame_fields(records[first:first + CHUNK])


def in_time_order(parts: list[np.ndarray]) -> np.ndarray:
    """Frame records of several rings (a bus's received and sent) as one, oldest first."""
    records = np.concatenate(parts) if len(parts) > 1 else parts[0]
    return records[np.argsort(records["t"], kind="stable")]


class RingReader:
    """A ring read by a process other than its producer's (the writer process)."""

    def __init__(self, shared: SharedFile, spec: RingSpec) -> None:
        self.spec, self._shared = spec, shared
        self._array = shared.array(spec)

    def count(self) -> int:
        return self._shared.count(self.spec)

    def read(self, since: int) -> tuple[int, np.ndarray]:
        """A copy of the records from number ``since`` on: (the first one's number,
        records). What the producer overwrote before or during the copy is left out, and
        so is the record in the slot it writes next (number ``count - capacity``: the
        producer writes there before it stores the count), so a full ring reads as its
        last ``capacity - 1`` records."""
        cap, arr = self.spec.capacity, self._array
        end = self.count()
        start = max(since, end - cap + 1, 0)
        if start >= end:
            return end, arr[:0].copy()
        k0, k1 = start % cap, end % cap
        out = arr[k0:k1].copy() if k0 < k1 else np.concatenate((arr[k0:], arr[:k1]))
        first_safe = self.count() - cap + 1  # overwritten while copying: dropped
        if first_safe > start:
            out = out[first_safe - start:]
            start = first_safe
        return start, out
