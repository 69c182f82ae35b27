"""``interface: inproc``: a CAN bus between threads of one process, cheap enough for 1 kHz.

python-can's ``virtual`` interface deep-copies every frame once per receiver and hands it
over through a ``queue.Queue``, a cost per receiver and frame. A bench of 12 simulated
drives on 4 buses at 1 kHz moves ~60,000 frame deliveries a second between the loop, the
simulated segments and the manager's node, which alone is more CPU than one core has. This
bus copies a frame once per send (the sender may re-fill its pre-allocated frame at once)
and shares that copy, read-only, with every receiver: one cost per send whatever the number
of receivers, and a ``deque`` per receiver instead of a locked queue.

Like ``virtual``: every bus opened on a channel name in this process sees the frames the
others send (not its own, unless ``receive_own_messages``), in order, stamped with
``time.time()`` at the send; nothing arbitrates or limits the rate. Unlike it, a receive
queue is bounded (``rx_queue_size`` frames, default 65536): a bus nobody reads drops its
oldest frames, as a SocketCAN socket does when its buffer is full, and counts them in
``rx_dropped``; a send never blocks. Received frames are shared between receivers: treat
them as read-only (python-can's own listeners do).

Two things a bench of several in-process buses needs: ``hold_wakeups`` (a burst's readers
are woken once, after it: the control loop's write and the simulator's answers each wake
the other side once per cycle, not at their first frame) and a CANopen master's filters
(one COB-ID each) checked as one set lookup per frame.

Registered with python-can as the interface ``inproc``
(``can.Bus(interface="inproc", channel="bench")``), so a config's bus section can name it.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any

import can
from can import BusABC, CanProtocol, Message

#: channel name -> the buses open on it (all of this process)
_channels: dict[str, list[InProcessBus]] = {}
_channels_lock = threading.Lock()

DEFAULT_RX_QUEUE_SIZE = 65536
#: a frame's copy is made field by field (every slot of Message is set; a test checks that
#: python-can has no slot this misses), without Message.__init__'s checks: the sender's
#: frame passed them, or was built with ``check=False`` as python-can's own readers build
_new_message = Message.__new__


def received(timestamp: float, arbitration_id: int, is_extended_id: bool,
             is_remote_frame: bool, is_error_frame: bool, channel: str, dlc: int,
             data: bytearray, is_fd: bool, bitrate_switch: bool,
             error_state_indicator: bool) -> Message:
    """A received frame, built field by field: ``Message()`` checks and converts, several
    times the cost, and every frame given here passed its checks when it was sent."""
    msg = _new_message(Message)
    msg.timestamp = timestamp
    msg.arbitration_id = arbitration_id
    msg.is_extended_id = is_extended_id
    msg.is_remote_frame = is_remote_frame
    msg.is_error_frame = is_error_frame
    msg.channel = channel
    msg.dlc = dlc
    msg.data = data
    msg.is_fd = is_fd
    msg.is_rx = True
    msg.bitrate_switch = bitrate_switch
    msg.error_state_indicator = error_state_indicator
    return msg


class InProcessBus(BusABC):
    """One endpoint on an in-process channel; see the module docstring."""

    def __init__(self, channel: Any = "inproc-0", receive_own_messages: bool = False,
                 rx_queue_size: int = DEFAULT_RX_QUEUE_SIZE, fd: bool = False,
                 **kwargs: Any) -> None:
        if rx_queue_size < 1:
            raise ValueError(f"inproc bus: rx_queue_size must be >= 1, got {rx_queue_size}")
        protocol = kwargs.pop("protocol", CanProtocol.CAN_FD if fd else CanProtocol.CAN_20)
        self._exact: frozenset[int] | None = None  # see _apply_filters (called by __init__)
        super().__init__(channel=channel, **kwargs)
        self.channel_id = str(channel)
        self.channel_info = f"in-process bus channel {self.channel_id}"
        self._can_protocol = protocol
        self.receive_own_messages = receive_own_messages
        self.rx_dropped = 0
        self._rx: collections.deque[Message] = collections.deque(maxlen=rx_queue_size)
        self._arrived = threading.Event()
        self._waiting = False
        self._wakeups: tuple[threading.Event, ...] = ()
        self._open = True
        self._peers: list[InProcessBus] = []
        self._holder = 0  # the thread holding wake-ups (see hold_wakeups)
        self._held = 0  # its hold_wakeups depth
        self._to_wake: list[InProcessBus] = []  # readers to wake at the release
        with _channels_lock:
            self._join([*_channels.get(self.channel_id, []), self])

    # ------------------------------------------------------------------ sending
    def send(self, msg: Message, timeout: float | None = None) -> None:
        """Deliver a copy of ``msg`` to every other bus on the channel; never blocks."""
        if not self._open:
            raise can.CanOperationError(f"{self.channel_info}: the bus is shut down")
        self._broadcast(received(time.time(), msg.arbitration_id, msg.is_extended_id,
                                 msg.is_remote_frame, msg.is_error_frame, self.channel_id,
                                 msg.dlc, bytearray(msg.data), msg.is_fd,
                                 msg.bitrate_switch, msg.error_state_indicator))

    def _broadcast(self, copy: Message) -> None:
        """Hand ``copy`` (this send's own, read-only from here on) to every other endpoint."""
        held = self._held and self._holder == threading.get_ident()
        for peer in self._peers:  # replaced on join/leave, never changed in place
            if (peer is not self or self.receive_own_messages) \
                    and peer._deliver(copy, not held) and held and peer not in self._to_wake:
                self._to_wake.append(peer)

    def hold_wakeups(self) -> None:
        """Until ``release_wakeups``: frames this thread sends here are queued at once (in
        order, stamped at their send) but their readers are woken only at the release. The
        sender of a burst (a cycle's RPDOs and SYNC on every bus) then wakes each reader once,
        after the burst, instead of at its first frame, where the reader would take the GIL
        from the sender mid-burst and see the burst in pieces. Frames other threads send
        meanwhile wake their readers at once. Nests; call from one thread at a time."""
        if not self._held:
            self._holder = threading.get_ident()
        self._held += 1

    def release_wakeups(self) -> None:
        """Wake the readers of the frames sent since ``hold_wakeups`` (at the outermost)."""
        if self._held <= 0:
            raise RuntimeError(f"{self.channel_info}: release_wakeups without hold_wakeups")
        self._held -= 1
        if not self._held:
            to_wake, self._to_wake = self._to_wake, []
            for peer in to_wake:
                peer._wake()

    def _deliver(self, msg: Message, wake: bool) -> bool:
        """Queue ``msg`` here if the filters take it (True), waking the reader if ``wake``."""
        if self._filters is not None and not self._wanted(msg):
            return False  # as a kernel filter: a frame the reader does not want never wakes it
        rx = self._rx
        if len(rx) == rx.maxlen:
            self.rx_dropped += 1
        rx.append(msg)
        if wake:
            self._wake()
        return True

    def set_filters(self, filters: can.typechecking.CanFilters | None = None) -> None:
        """As python-can's, but the set lookup (``_apply_filters``) is made first: python-can
        stores the new filters before applying them, and a frame another thread sends in
        between would be judged by the old set (an e-stop COB-ID changed at run time)."""
        self._apply_filters(filters)
        super().set_filters(filters)

    def _apply_filters(self, filters: can.typechecking.CanFilters | None) -> None:
        """Filters that each take one 11-bit identifier (mask 0x7FF, extended False: what a
        CANopen master sets, one per COB-ID it reads) are checked as one set lookup per
        frame; python-can's own check loops over the filters, a cost per filter and frame."""
        exact = None
        if filters and all(f.get("extended") is False and f["can_mask"] == 0x7FF
                           for f in filters):
            exact = frozenset(f["can_id"] & 0x7FF for f in filters)
        self._exact = exact

    def _wanted(self, msg: Message) -> bool:
        exact = self._exact
        if exact is not None:
            return not msg.is_extended_id and msg.arbitration_id in exact
        return self._matches_filters(msg)

    def _wake(self) -> None:
        if self._waiting:  # the reader set this before its last look at the queue
            self._arrived.set()
        for wakeup in self._wakeups:
            if not wakeup.is_set():
                wakeup.set()

    # ------------------------------------------------------------------ receiving
    def _wait(self, timeout: float | None) -> bool:
        """True once a frame is queued; False after ``timeout`` s (None: no limit)."""
        if self._rx:
            return True
        if timeout is not None and timeout <= 0:
            return False
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self._arrived.clear()
            self._waiting = True
            try:
                if self._rx:
                    return True
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._arrived.wait(left)
            finally:
                self._waiting = False
            if self._rx or not self._open:
                return bool(self._rx)

    def _recv_internal(self, timeout: float | None) -> tuple[Message | None, bool]:
        if not self._open:
            raise can.CanOperationError(f"{self.channel_info}: the bus is shut down")
        if not self._wait(timeout):
            return None, False
        return self._rx.popleft(), False

    def recv_batch(self, timeout: float, limit: int) -> list[Message]:
        """Up to ``limit`` queued frames after waiting up to ``timeout`` s for the first
        (what frame_io.FrameReader reads with: one wait per batch, no per-frame overhead)."""
        if not self._open:
            raise can.CanOperationError(f"{self.channel_info}: the bus is shut down")
        if not self._wait(timeout):
            return []
        rx = self._rx
        batch: list[Message] = []
        while rx and len(batch) < limit:
            msg = rx.popleft()
            if self._filters is None or self._wanted(msg):
                batch.append(msg)
        return batch

    @property
    def pending(self) -> bool:
        """A frame is queued, or the bus is shut down (a read says so at once)."""
        return bool(self._rx) or not self._open

    def add_wakeup(self, event: threading.Event) -> None:
        """Set ``event`` whenever a frame is queued here: one thread can wait for frames on
        several buses (frame_io.BusSelector) and then read each with a zero timeout. The
        bus's one reader adds and removes its wake-up (no lock: one writer)."""
        self._wakeups = (*self._wakeups, event)

    def remove_wakeup(self, event: threading.Event) -> None:
        self._wakeups = tuple(e for e in self._wakeups if e is not event)

    # ------------------------------------------------------------------ life cycle
    def shutdown(self) -> None:
        super().shutdown()
        if not self._open:
            return
        self._open = False
        with _channels_lock:
            self._join([p for p in self._peers if p is not self])
        self._arrived.set()  # a reader waiting in recv sees the bus closed
        for wakeup in self._wakeups:  # and one waiting on several buses reads this one
            wakeup.set()

    def _join(self, peers: list[InProcessBus]) -> None:
        """Give every endpoint of the channel the new list of endpoints (lock held). Lists
        are replaced, never changed in place, so a send iterating the old one is safe."""
        if peers:
            _channels[self.channel_id] = peers
        else:
            _channels.pop(self.channel_id, None)
        for peer in peers:
            peer._peers = peers
