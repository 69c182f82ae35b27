"""Files a user names are read only when they are regular files (rocoma_can/user_files.py):
an EDS given as a FIFO, a directory or a device is refused in one line, at once, by the
device-file reader, by check-config and by ``demo --eds`` (each hung on a FIFO)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from fixtures.configs import good
from fixtures.fifo import FIFO_WAIT, fifo, without_hanging

from rocoma_can.drivers.files.device_file import (
    MAX_DEVICE_FILE_BYTES,
    DeviceFileError,
    read_device_file,
)
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


def test_a_zenoh_config_file_is_read_here_json5_or_yaml_and_never_a_fifo(tmp_path):
    """zenoh.config_file: read by rocoma-can (Zenoh's own reader waited on a FIFO in native
    code, holding the interpreter: not even Ctrl-C ended run), JSON5 or YAML."""
    zenoh = pytest.importorskip("zenoh")
    from rocoma_can.fleet.bridge import _config_from
    (tmp_path / "z.json5").write_text("{mode: 'client', // a comment\n}")
    (tmp_path / "z.yaml").write_text("mode: client\n")
    for name in ("z.json5", "z.yaml"):
        assert json.loads(_config_from(zenoh, str(tmp_path / name)).get_json("mode")) \
            == "client"
    with fifo(tmp_path / "z.json5.fifo") as path:
        caught = without_hanging(lambda: _config_from(zenoh, str(path)))
    assert isinstance(caught, ValueError)
    assert str(caught) == f"{path}: a FIFO (named pipe), not a regular file"


@pytest.mark.parametrize("what", ["fifo", "missing"])
def test_check_config_says_a_zenoh_config_file_it_cannot_read(tmp_path, what):
    config = good()
    config["zenoh"] = {"prefix": "r", "config_file": "z.json5"}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(config))
    if what == "fifo":
        with fifo(tmp_path / "z.json5"):
            done = subprocess.run([sys.executable, "-m", "rocoma_can", "check-config",
                                   str(path)], capture_output=True, text=True,
                                  timeout=FIFO_WAIT + 30)
        said = "is a FIFO (named pipe), not a regular file"
    else:
        done = subprocess.run([sys.executable, "-m", "rocoma_can", "check-config", str(path)],
                              capture_output=True, text=True, timeout=60)
        said = ": No such file or directory"
    assert done.returncode == 2, done
    assert f"{path}: zenoh.config_file: {tmp_path}/z.json5{' ' if what == 'fifo' else ''}" \
        f"{said}" in done.stdout, done.stdout


def test_a_device_file_past_the_size_limit_is_refused_unparsed(tmp_path):
    """A wrong file (a log, an image) named as an EDS costs a bounded read, then one line."""
    path = tmp_path / "huge.eds"
    with path.open("wb") as f:
        f.write(b"[1000]\nParameterName=Device type\n")
        f.truncate(MAX_DEVICE_FILE_BYTES + 1)
    with pytest.raises(DeviceFileError, match=r"huge.eds: larger than 8 MiB; not an EDS/DCF"):
        read_device_file(str(path))
