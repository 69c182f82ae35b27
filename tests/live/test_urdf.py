"""The config's URDF (rocoma_can/live/urdf.py): its joints' transforms against ones computed by
hand, hostile and broken files refused in one line naming the file, and ``urdf:`` checked
with the config (rocoma_can/runtime/config_check.py)."""
from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from fixtures.configs import good
from fixtures.fifo import FIFO_WAIT, fifo, without_hanging

from rocoma_can.cli.demo.config import demo_urdf
from rocoma_can.cli.main import main
from rocoma_can.live.urdf import MAX_URDF_BYTES, Robot, UrdfError, parse_urdf, read_urdf
from rocoma_can.runtime.config import ConfigError, load, validate

S = math.sqrt(0.5)  # sin and cos of 45 degrees

#: base -a-> upper -b-> fore -tool-> tool, and a slide on the base; a (about z) at 0.1 m
#: over the base, b (about y) 0.5 m up the upper arm, the tool 0.4 m up the forearm turned a
#: quarter about x; the slide's axis is x in a joint frame turned a quarter about z
ARM = """<?xml version="1.0"?>
<robot name="arm">
  <link name="base"/><link name="upper"/><link name="fore"/><link name="tool"/>
  <link name="carriage"/>
  <joint name="a" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 2"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="b" type="continuous"><parent link="upper"/><child link="fore"/>
    <origin xyz="0 0 0.5"/><axis xyz="0 1 0"/></joint>
  <joint name="tool" type="fixed"><parent link="fore"/><child link="tool"/>
    <origin xyz="0 0 0.4" rpy="1.5707963267948966 0 0"/></joint>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage"/>
    <origin xyz="1 0 0" rpy="0 0 1.5707963267948966"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""


def _arm():
    return parse_urdf(ARM.encode(), "arm.urdf")


def _close(got, expected):
    assert got == pytest.approx(expected, abs=1e-12)


def test_each_joint_at_its_position():
    robot = _arm()
    assert robot.name == "arm" and robot.movable == ("a", "b", "slide")
    a, b, tool, slide = robot.transforms({"a": math.pi / 2, "b": math.pi / 2, "slide": 0.2,
                                          "tool": 5.0})  # a fixed joint takes no position
    assert (a.parent, a.child, b.parent, b.child) == ("base", "upper", "upper", "fore")
    _close(a.translation, (0, 0, 0.1))
    _close(a.rotation, (0, 0, S, S))  # a quarter about z (the axis 0 0 2, made a unit)
    _close(b.translation, (0, 0, 0.5))
    _close(b.rotation, (0, S, 0, S))  # a quarter about y
    _close(tool.translation, (0, 0, 0.4))
    _close(tool.rotation, (S, 0, 0, S))  # its rpy: a quarter about x
    # the slide's x is the base's y: its origin turned a quarter about z
    _close(slide.translation, (1, 0.2, 0))
    _close(slide.rotation, (0, 0, S, S))


def _matrix(q):
    x, y, z, w = q
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]


def _apply(m, v):
    return [sum(m[r][c] * v[c] for c in range(3)) for r in range(3)]


def test_the_chain_puts_the_tool_where_the_arm_reaches():
    """Composed from base to tool, by hand: b tips the forearm's 0.4 m from z to x, a turns
    x to y: the tool's origin is 0.4 m along y, 0.1 + 0.5 m up. The tool's z: its rpy turns
    it to -y, b keeps -y, a turns -y to x."""
    a, b, tool, _ = _arm().transforms({"a": math.pi / 2, "b": math.pi / 2})
    ra, rb = _matrix(a.rotation), _matrix(b.rotation)
    origin = [p + q for p, q in zip(a.translation, _apply(ra, [
        u + v for u, v in zip(b.translation, _apply(rb, tool.translation))]))]
    _close(origin, (0, 0.4, 0.6))
    tool_z = _apply(ra, _apply(rb, _apply(_matrix(tool.rotation), [0, 0, 1])))
    _close(tool_z, (1, 0, 0))


def test_rpy_is_roll_then_pitch_then_yaw_about_fixed_axes():
    text = ARM.replace('xyz="0 0 0.4" rpy="1.5707963267948966 0 0"',
                       'xyz="0 0 0.4" rpy="1.5707963267948966 0 1.5707963267948966"')
    tool = parse_urdf(text.encode(), "arm.urdf").transforms({})[2]
    _close(tool.rotation, (0.5, 0.5, 0.5, 0.5))  # Rz(90) Rx(90): qz * qx by hand


def test_a_joint_without_a_finite_position_stands_at_its_origin():
    a = _arm().transforms({"a": math.nan})[0]
    _close(a.rotation, (0, 0, 0, 1))


def test_the_demo_arm_has_a_joint_per_drive():
    robot = parse_urdf(demo_urdf(["joint1", "joint2", "joint3"]).encode(), "demo")
    assert robot.movable == ("joint1", "joint2", "joint3")
    assert robot.links[0] == "base_link"


BILLION_LAUGHS = """<?xml version="1.0"?>
<!DOCTYPE robot [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>
<robot name="&b;"/>"""
EXTERNAL = """<?xml version="1.0"?>
<!DOCTYPE robot [<!ENTITY secret SYSTEM "file:///etc/passwd">]><robot name="&secret;"/>"""


@pytest.mark.parametrize("text, expected", [
    (BILLION_LAUGHS, "DOCTYPE or ENTITY declaration; refused"),
    (EXTERNAL, "DOCTYPE or ENTITY declaration; refused"),
    ("<robot><link name='a'>", "not XML (no element found"),
    ("solid mesh\nfacet normal 0 0 1\n", "not XML (syntax error"),
    ("<sdf version='1.6'/>", "no <robot> root element (found <sdf>)"),
    ("<robot><link/></robot>", "<link> 1 has no name"),
    ("<robot><link name='a'/><link name='a'/></robot>", "two links named 'a'"),
    ("<robot><link name='a'/><link name='b'/><joint type='fixed'><parent link='a'/>"
     "<child link='b'/></joint></robot>", "<joint> 1 has no name"),
    ("<robot><link name='a'/><link name='b'/><joint name='j'><parent link='a'/>"
     "<child link='b'/></joint></robot>", "joint 'j': type None is none of"),
    ("<robot><link name='a'/><link name='b'/><joint name='j' type='hinge'><parent "
     "link='a'/><child link='b'/></joint></robot>", "joint 'j': type 'hinge' is none of"),
    ("<robot><link name='a'/><link name='b'/><joint name='j' type='fixed'><parent/>"
     "<child link='b'/></joint></robot>", "joint 'j': no <parent link=...>"),
    ("<robot><link name='a'/><joint name='j' type='fixed'><parent link='a'/>"
     "<child link='b'/></joint></robot>", "joint 'j': no link named 'b'"),
    ("<robot><link name='a'/><link name='b'/><joint name='j' type='revolute'><parent "
     "link='a'/><child link='b'/><origin xyz='1 2'/></joint></robot>",
     "joint 'j': xyz='1 2' is not three numbers"),
    ("<robot><link name='a'/><link name='b'/><joint name='j' type='revolute'><parent "
     "link='a'/><child link='b'/><origin rpy='nan 0 0'/></joint></robot>",
     "joint 'j': rpy='nan 0 0' is not finite"),
    ("<robot><link name='a'/><link name='b'/><joint name='j' type='revolute'><parent "
     "link='a'/><child link='b'/><axis xyz='0 0 0'/></joint></robot>",
     "joint 'j': <axis xyz> is zero"),
    ("<robot><link name='a'/><link name='b'/><joint name='j' type='fixed'><parent "
     "link='a'/><child link='b'/></joint><joint name='k' type='fixed'><parent link='b'/>"
     "<child link='a'/></joint></robot>", "no root link: its joints make a loop"),
    ("<robot><link name='a'/><link name='b'/></robot>", "2 root links (a, b)"),
    ("<robot><link name='a'/><link name='b'/><link name='c'/><joint name='j' type='fixed'>"
     "<parent link='a'/><child link='c'/></joint><joint name='k' type='fixed'><parent "
     "link='b'/><child link='c'/></joint></robot>",
     "link 'c' is the child of joints 'j' and 'k'"),
])
def test_a_broken_or_hostile_urdf_is_one_line_naming_the_file(text, expected):
    with pytest.raises(UrdfError) as caught:
        parse_urdf(text.encode(), "bad.urdf")
    message = str(caught.value)
    assert message.startswith("bad.urdf: ") and expected in message, message
    assert "\n" not in message


def test_a_huge_file_is_refused_unread(tmp_path):
    path = tmp_path / "huge.urdf"
    with path.open("wb") as f:  # a robot that is valid at its start
        f.write(b"<robot name='x'><link name='a'/>" + b" " * MAX_URDF_BYTES + b"</robot>")
    with pytest.raises(UrdfError, match=rf"huge.urdf: larger than {MAX_URDF_BYTES} bytes"):
        read_urdf(path)


def test_a_binary_file_is_not_utf8(tmp_path):
    path = tmp_path / "mesh.urdf"
    path.write_bytes(b"\x80\x81binary")
    with pytest.raises(UrdfError, match=r"mesh.urdf: not UTF-8 text \(invalid start byte"):
        read_urdf(path)


@pytest.mark.parametrize("kind", ["fifo", "directory", "device"])
def test_only_a_regular_file_is_read(tmp_path, kind):
    """A FIFO would keep the read waiting for a writer (check-config and run hung), a
    device could go on for ever: each is refused, unread, in one line."""
    path = tmp_path / "robot.urdf"
    if kind == "fifo":
        with fifo(path):
            caught = without_hanging(lambda: read_urdf(path))
    else:
        if kind == "directory":
            path.mkdir()
        else:
            path = Path("/dev/zero")
        caught = without_hanging(lambda: read_urdf(path))
    expected = {"fifo": "a FIFO (named pipe)", "directory": "a directory",
                "device": "a character device"}[kind]
    assert isinstance(caught, UrdfError)
    assert str(caught) == f"{path}: {expected}, not a regular file; a URDF is read from a file"


# --- urdf: in the config ------------------------------------------------------------------

def _robot(tmp_path, joints=("j1", "j2"), extra=""):
    links = "".join(f"<link name='l{i}'/>" for i in range(len(joints) + 1))
    chain = "".join(f"<joint name='{name}' type='revolute'><parent link='l{i}'/><child "
                    f"link='l{i + 1}'/><axis xyz='0 0 1'/></joint>"
                    for i, name in enumerate(joints))
    (tmp_path / "urdf").mkdir(exist_ok=True)
    (tmp_path / "urdf" / "robot.urdf").write_text(f"<robot name='r'>{links}{chain}{extra}</robot>")


def _config_file(tmp_path, **top):
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump({**good(), **top}))
    return path


def test_the_urdf_is_read_relative_to_the_config_file(tmp_path):
    _robot(tmp_path, joints=("j1", "j2", "wrist"))
    config = load(_config_file(tmp_path, urdf="urdf/robot.urdf"))
    assert config.robot is not None and config.robot.movable == ("j1", "j2", "wrist")
    assert config.notes == [f"urdf: {tmp_path}/urdf/robot.urdf: no drive moves wrist: shown "
                            "at the origin"]


def test_without_urdf_there_is_no_robot():
    assert validate(good()).robot is None


@pytest.mark.parametrize("value, joints, expected", [
    ("urdf/missing.urdf", ("j1", "j2"),
     "urdf: {dir}/urdf/missing.urdf: cannot read: No such file or directory"),
    (["robot.urdf"], ("j1", "j2"), "urdf: expected the path of a URDF file, got ['robot.urdf']"),
    ("urdf/robot.urdf", ("j1", "elbow"),
     "urdf: {dir}/urdf/robot.urdf has no joint named 'j2' (a drive's name); its movable "
     "joints: j1, elbow"),
])
def test_urdf_problems_name_the_key_and_the_file(tmp_path, value, joints, expected):
    _robot(tmp_path, joints=joints)
    path = _config_file(tmp_path, urdf=value)
    with pytest.raises(ConfigError) as caught:
        load(path)
    assert caught.value.problems == [f"{path}: {expected.format(dir=tmp_path)}"]


def test_a_drive_on_a_fixed_joint_would_never_move(tmp_path):
    _robot(tmp_path, joints=("j1",), extra="<link name='l9'/><joint name='j2' type='fixed'>"
                                           "<parent link='l1'/><child link='l9'/></joint>")
    with pytest.raises(ConfigError, match=r"joint 'j2' \(a drive's name\) is fixed: the view "
                                          "would never move it"):
        load(_config_file(tmp_path, urdf="urdf/robot.urdf"))


def test_check_config_refuses_a_fifo_as_the_urdf(tmp_path):
    """check-config (and run, which loads the config the same way) on a config whose
    urdf: is a FIFO: a usage error naming the key and the path, at once."""
    config = _config_file(tmp_path, urdf="arm.urdf")
    with fifo(tmp_path / "arm.urdf"):
        done = subprocess.run([sys.executable, "-m", "rocoma_can.cli.main", "check-config",
                               str(config)], capture_output=True, text=True,
                              timeout=FIFO_WAIT + 30)
    assert done.returncode == 2, done
    assert done.stdout.splitlines() == [
        f"{config}: urdf: {tmp_path}/arm.urdf: a FIFO (named pipe), not a regular file; a "
        "URDF is read from a file", "1 problem(s)"]
    assert "Traceback" not in done.stderr


def test_check_config_says_a_broken_urdf_in_one_line(tmp_path, capsys):
    (tmp_path / "arm.urdf").write_text(BILLION_LAUGHS)
    assert main(["check-config", str(_config_file(tmp_path, urdf="arm.urdf"))]) == 2
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith("arm.urdf: has a DOCTYPE or ENTITY declaration; refused (a URDF "
                           "needs none, and entities can expand without bound or read files)")
    assert out[1:] == ["1 problem(s)"]


# -- a big robot costs what its size does, and is read once --------------------------------

def chain(links: int, name: str = "big") -> bytes:
    """A robot of ``links`` links in one chain, each joint revolute (a long snake)."""
    parts = [f'<robot name="{name}">', '<link name="l0"/>']
    for i in range(1, links):
        parts.append(f'<link name="l{i}"/><joint name="j{i}" type="revolute"><parent '
                     f'link="l{i - 1}"/><child link="l{i}"/><axis xyz="0 0 1"/></joint>')
    return ("\n".join(parts) + "</robot>").encode()


def _lines_run(work: Callable[[], object]) -> int:
    """How many Python lines ``work`` runs in rocoma_can's URDF module (a count of the work
    done, the same on any machine: no clock)."""
    import rocoma_can.live.urdf as module
    count = 0

    def tracer(frame, event, arg):
        nonlocal count
        if frame.f_code.co_filename == module.__file__:
            if event == "line":
                count += 1
            return tracer
        return None
    sys.settrace(tracer)
    try:
        work()
    finally:
        sys.settrace(None)
    return count


def test_reading_a_urdf_grows_with_its_size_not_its_square():
    """A 1.4 MB URDF of 14,000 links took 16 s: every joint was compared with every joint
    before it (names, children, the roots). Four times the links must cost about four
    times the work."""
    small = _lines_run(lambda: parse_urdf(chain(250), "small.urdf"))
    large = _lines_run(lambda: parse_urdf(chain(1000), "large.urdf"))
    assert large <= 5 * small, (small, large)


def test_the_largest_robot_the_size_limit_lets_in_is_read():
    text = chain(14_000)
    assert 1_400_000 <= len(text) <= MAX_URDF_BYTES
    robot = parse_urdf(text, "snake.urdf")
    assert len(robot.links) == 14_000 and len(robot.joints) == 13_999
    assert robot.joints[-1].parent == "l13998"


def test_an_empty_robot_is_said_to_be_empty():
    """``<robot name="r"/>`` has no joints to make a loop: it has no links at all."""
    with pytest.raises(UrdfError) as caught:
        parse_urdf(b'<robot name="r"/>', "empty.urdf")
    assert str(caught.value) == "empty.urdf: robot 'r' has no <link>: an empty robot"


def test_a_loop_beside_a_tree_is_found():
    """One link with no parent (the root) and two links that are each other's child: the
    root count alone took it for one tree."""
    text = ("<robot><link name='root'/><link name='a'/><link name='b'/>"
            "<joint name='j' type='fixed'><parent link='a'/><child link='b'/></joint>"
            "<joint name='k' type='fixed'><parent link='b'/><child link='a'/></joint>"
            "</robot>")
    with pytest.raises(UrdfError) as caught:
        parse_urdf(text.encode(), "loop.urdf")
    assert str(caught.value) == ("loop.urdf: links a, b are not under the root link 'root': "
                                 "their joints make a loop")


def test_the_urdf_of_a_run_is_parsed_once(tmp_path, monkeypatch):
    """check-config's reading is the one `run` uses, and the recording's writer process
    (the live view, the recording's /tf) takes the robot read, not the text to read again."""
    import io
    import json
    import os
    import xml.etree.ElementTree as ET

    from rocoma_can.record.rings import SharedFile, layout
    from rocoma_can.record.trace import RowLayout
    from rocoma_can.record.writer import Spec, Writer
    parses = []
    real = ET.fromstring
    monkeypatch.setattr(ET, "fromstring", lambda *a, **k: parses.append(1) or real(*a, **k))
    _robot(tmp_path, joints=("j1", "j2"))
    config = load(_config_file(tmp_path, urdf="urdf/robot.urdf"))
    assert config.robot is not None and len(parses) == 1
    [rows] = layout([("rows", 64, RowLayout(["j1", "j2"]).width, False)])
    shared = SharedFile(rows.size)
    try:
        spec = Spec(os.dup(shared.fd), shared.size, rows, {}, ["j1", "j2"], {},
                    robot=config.robot.as_json())
        writer = Writer(Spec.from_json(spec.to_json()), io.StringIO())
        writer.close()
    finally:
        shared.close()
    assert len(parses) == 1
    assert Robot.from_json(json.loads(json.dumps(config.robot.as_json()))) == config.robot
