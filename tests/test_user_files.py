"""Files a user names are read only when they are regular files (rocoma_can/user_files.py):
an EDS given as a FIFO, a directory or a device is refused in one line, at once, by the
device-file reader, by check-config and by ``demo --eds`` (each hung on a FIFO)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from fixtures.fifo import FIFO_WAIT, fifo, without_hanging
from test_config import good

from rocoma_can.drivers.device_file import DeviceFileError, read_device_file
from rocoma_can.user_files import NotRegularFile, read_regular


def test_a_regular_file_is_read_up_to_its_limit(tmp_path):
    (tmp_path / "f").write_bytes(b"abcdef")
    assert read_regular(tmp_path / "f") == b"abcdef"
    assert read_regular(tmp_path / "f", 4) == b"abcd"


@pytest.mark.parametrize("what", ["fifo", "directory", "device"])
def test_the_device_file_reader_refuses_what_is_no_regular_file(tmp_path, what):
    expected = {"fifo": "a FIFO (named pipe)", "directory": "a directory",
                "device": "a character device"}[what]
    path = tmp_path / "drive.eds"
    if what == "fifo":
        with fifo(path):
            caught = without_hanging(lambda: read_device_file(str(path)))
    else:
        if what == "directory":
            path.mkdir()
        else:
            path = Path("/dev/zero")
        caught = without_hanging(lambda: read_device_file(str(path)))
    assert isinstance(caught, DeviceFileError)
    assert str(caught) == f"{path}: cannot read ({expected}, not a regular file)"
    if what != "fifo":  # (the FIFO is gone with its context)
        with pytest.raises(NotRegularFile) as raised:
            read_regular(path)
        assert raised.value.strerror == f"{expected}, not a regular file"


def test_check_config_and_the_demo_refuse_a_fifo_as_the_eds(tmp_path):
    config = good()
    config["drives"][0]["eds"] = "drive.eds"
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(config))
    with fifo(tmp_path / "drive.eds"):
        checked = subprocess.run([sys.executable, "-m", "rocoma_can", "check-config",
                                  str(path)], capture_output=True, text=True,
                                 timeout=FIFO_WAIT + 30, cwd=tmp_path)
        demo = subprocess.run([sys.executable, "-m", "rocoma_can", "demo", "--eds",
                               "drive.eds", "--no-record", "--duration", "1"],
                              capture_output=True, text=True, timeout=FIFO_WAIT + 60,
                              cwd=tmp_path)
    assert checked.returncode == 2, checked
    assert f"eds file '{tmp_path}/drive.eds' is a FIFO (named pipe), not a regular file" \
        in checked.stdout, checked.stdout
    assert demo.returncode == 2, demo
    assert demo.stdout.splitlines() == [
        "demo: --eds: drive.eds: cannot read (a FIFO (named pipe), not a regular file)"], demo
    assert "Traceback" not in checked.stderr + demo.stderr
