"""One python-can bus with a canopen Network on it.

canopen is used only for what it is good at (EDS import, SDO, NMT); the cycle sends and
receives raw frames on the same bus. The Network's Notifier is the only reader of the bus
(python-can allows one per bus), so the driver's receive path is a listener on it.
"""
from __future__ import annotations

import logging
import socket
from typing import Any

import can
import canopen

log = logging.getLogger(__name__)

#: Receive buffer for SocketCAN sockets: a frame costs ~1 KiB of socket memory, so the
#: default (~200 KiB) holds a few hundred frames, a fraction of a second of a busy bus; a
#: stalled reader (GC, scheduler) would lose TPDOs and heartbeats.
RECEIVE_BUFFER_BYTES = 4 << 20


def enlarge_receive_buffer(sock: socket.socket, size: int = RECEIVE_BUFFER_BYTES) -> None:
    """Best effort: SO_RCVBUFFORCE (root / CAP_NET_ADMIN) or SO_RCVBUF up to rmem_max."""
    force = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux's value; Python may not name it
    for option in (force, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, size)
            return
        except OSError:
            continue


def open_bus(interface: str, channel: str, bitrate: int | None = None,
             **kwargs: Any) -> can.BusABC:
    """A python-can bus that ignores ~/.canrc and CAN_* variables (the config says it all)."""
    if bitrate is not None:
        kwargs["bitrate"] = bitrate
    try:
        return can.Bus(interface=interface, channel=channel, ignore_config=True, **kwargs)
    except (OSError, can.CanError) as e:
        raise OSError(f"cannot open CAN bus {interface}:{channel}: {e}") from e


class CanopenBus:
    """A bus (opened here or lent by the caller) plus a canopen Network listening on it."""

    def __init__(self, bus: can.BusABC, own_bus: bool = False) -> None:
        self.bus = bus
        self.own_bus = own_bus
        sock = getattr(bus, "socket", None)
        if isinstance(sock, socket.socket):
            enlarge_receive_buffer(sock)
        self.network = canopen.Network(bus)
        self.network.connect()  # with a bus given, this only starts the Notifier

    def add_listener(self, listener: can.Listener) -> None:
        assert self.network.notifier is not None
        self.network.notifier.add_listener(listener)

    def close(self) -> None:
        """Stop the Notifier (joins its thread); shut the bus only if it was opened here."""
        notifier = self.network.notifier
        if notifier is not None:
            notifier.stop(timeout=2.0)
            self.network.notifier = None
        if self.own_bus:
            self.bus.shutdown()
