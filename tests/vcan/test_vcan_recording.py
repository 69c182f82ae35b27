"""rocoma_can/record/can_log.py, rocoma_can/cli/record.py: recording on real SocketCAN: `rocoma-can
record` (a process of its own, a passive socket) writes what an independent socket sees, and
can-utils' `canplayer` replays the file onto vcan0 frame for frame. Asserts frames and order, never
speed (user-mode-linux)."""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import can

BIN = Path(sys.executable).parent / "rocoma-can"
#: Bound for a command's start and end in the guest (no supervision to derive it from):
#: a CLI start alone costs ~8.5 s there and once took over 60 s on a loaded host; the
#: same bound as the end-to-end tests' CLI calls (test_e2e_manager.cli).
PROCESS_BOUND = 180.0


def frames() -> list[can.Message]:
    """Standard ids of every length, an extended id, a remote frame: what candump's format
    and canplayer carry."""
    out = [can.Message(arbitration_id=0x181 + k % 7, data=bytes(range(k % 9)),
                       is_extended_id=False) for k in range(30)]
    out.append(can.Message(arbitration_id=0x1ABCDE01, data=b"\x01\x02\x03",
                           is_extended_id=True))
    out.append(can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=1,
                           is_extended_id=False))
    return out


def key(msg: can.Message) -> tuple[int, bytes, bool, bool]:
    data = b"" if msg.is_remote_frame else bytes(msg.data)
    return msg.arbitration_id, data, msg.is_extended_id, msg.is_remote_frame


def receive(bus: can.BusABC, count: int) -> list[can.Message]:
    got = []
    deadline = time.monotonic() + PROCESS_BOUND
    while len(got) < count and time.monotonic() < deadline:
        msg = bus.recv(timeout=1.0)
        if msg is not None:
            got.append(msg)
    return got


def test_record_writes_what_a_socket_sees_and_canplayer_replays_it(tmp_path, bus_factory):
    path = tmp_path / "vcan0.log"
    sender = bus_factory("vcan0", "socketcan")
    listener = bus_factory("vcan0", "socketcan")
    recorder = subprocess.Popen([str(BIN), "record", str(path), "--interface", "socketcan",
                                 "--channel", "vcan0"], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
    try:
        # the recorder opens its socket before it creates the file: once the file exists,
        # every frame sent is queued for it
        deadline = time.monotonic() + PROCESS_BOUND
        while not path.exists() and recorder.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert path.exists(), f"the recorder did not start: rc {recorder.poll()}"
        sent = frames()
        for msg in sent:
            sender.send(msg)
        seen = receive(listener, len(sent))
        assert [key(m) for m in seen] == [key(m) for m in sent]
        time.sleep(0.5)  # the recorder's reader drains its socket
    finally:
        recorder.send_signal(signal.SIGTERM)
        out, _ = recorder.communicate(timeout=PROCESS_BOUND)
    assert recorder.returncode == 0, out
    assert f"{len(sent)} frames written to {path}" in out, out
    recorded = list(can.LogReader(str(path)))
    assert [key(m) for m in recorded] == [key(m) for m in seen]
    assert all(m.channel == "vcan0" for m in recorded)

    replayed_on = bus_factory("vcan0", "socketcan")
    player = subprocess.run(["canplayer", "-I", str(path)], capture_output=True, text=True,
                            timeout=PROCESS_BOUND)
    assert player.returncode == 0, player.stderr
    replayed = receive(replayed_on, len(recorded))
    assert [key(m) for m in replayed] == [key(m) for m in recorded]
