"""rocoma_can/record/can_log.py, rocoma_can/cli/record.py (``record``): raw CAN files that
python-can reads back, frame for frame, and a file the verb refuses to write in one line."""
from __future__ import annotations

import threading
import time

import can
import pytest

from rocoma_can.cli.main import main


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_record_writes_what_an_independent_listener_sees(suffix, tmp_path, bus_factory,
                                                        virtual_channel):
    path = tmp_path / f"bus{suffix}"
    sender, listener = bus_factory(), bus_factory()
    done: dict[str, int] = {}
    recorder = threading.Thread(target=lambda: done.setdefault("rc", main([
        "record", str(path), "--interface", "virtual", "--channel", virtual_channel,
        "--duration", "1.5"])))
    recorder.start()
    time.sleep(0.5)  # the recorder's bus is open
    sent = [can.Message(arbitration_id=0x180 + k % 8, data=bytes([k, k + 1]),
                        is_extended_id=False) for k in range(40)]
    for msg in sent:
        sender.send(msg)
    seen = [listener.recv(1.0) for _ in sent]
    recorder.join(10.0)
    assert done == {"rc": 0}
    got = [m for m in can.LogReader(str(path))]
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == \
        [(m.arbitration_id, bytes(m.data)) for m in seen]


@pytest.mark.parametrize("suffix", [".asc", ".blf"])
def test_a_channel_named_with_many_digits_is_written_as_channel_1(suffix, tmp_path):
    """python-can numbers a channel by the digits its name ends in: an in-process bus named
    by a random id ("...-98765432") does not fit BLF's 16 bits; it is the file's channel 1,
    and the received frame is not changed (other receivers share it)."""
    from rocoma_can.record.can_log import FrameLog
    frame_log = FrameLog(tmp_path / f"x{suffix}").start()
    msg = can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False,
                      channel="rocoma-98765432", timestamp=1.0)
    frame_log.on_message_received(msg)
    frame_log.stop()
    assert frame_log.error is None and frame_log.frames == 1
    assert msg.channel == "rocoma-98765432"
    (got,) = list(can.LogReader(str(tmp_path / f"x{suffix}")))
    assert (got.arbitration_id, bytes(got.data), got.channel) == (0x181, b"\x01\x02", 0)


def test_record_refuses_an_unknown_format_or_missing_directory(tmp_path, capsys):
    assert main(["record", str(tmp_path / "x.txt"), "--interface", "virtual",
                 "--channel", "r", "--duration", "0.1"]) == 2
    assert main(["record", str(tmp_path / "no" / "x.log"), "--interface", "virtual",
                 "--channel", "r", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "unknown recording format '.txt'" in err and "does not exist" in err


def test_record_refuses_a_file_that_exists(tmp_path, capsys):
    """`record bus.log` again wrote over the last capture without a word."""
    path = tmp_path / "bus.log"
    path.write_text("(1.000000) can0 701#05\n")
    assert main(["record", str(path), "--interface", "virtual", "--channel", "r",
                 "--duration", "0.1"]) == 2
    assert capsys.readouterr().err == (
        f"rocoma-can: {path}: exists: an earlier recording is not written over; give "
        "another file, or move it\n")
    assert path.read_text() == "(1.000000) can0 701#05\n"
