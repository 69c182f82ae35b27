"""The robot of the config's ``urdf:``: read strictly, and its joints' transforms at given
positions, which Foxglove's 3D panel needs to move the links it draws (its URDF layer places
each link at the joint's origin and moves it only by the transforms it is sent: a robot
state publisher's job, done here).

The file is read as hostile input: a regular file (a FIFO or a device could keep the read
waiting forever), at most MAX_URDF_BYTES, UTF-8, no DOCTYPE (so no entity,
internal or external: "billion laughs" and file reads are refused before the XML parser
sees the text), a ``<robot>`` root, every link and joint complete. Each error is UrdfError
with one line naming the file and what is wrong with it.

Kinematics per joint (URDF: origin ``xyz``/``rpy`` in the parent link's frame, ``axis`` in
the joint's frame after its origin): revolute and continuous rotate about the axis by the
position, prismatic slide along it, fixed (and floating, planar: nothing here moves them)
stay at the origin. Pure Python: a few joints at the view's rate need no numpy.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from ..errors import RocomaError
from ..user_files import NotRegularFile, read_regular

#: a URDF is text without meshes (those are files of their own): this bounds what a hostile
#: or wrong file (a mesh, a log) can cost to read
MAX_URDF_BYTES = 2 << 20
#: joints a drive can move in the view
MOVABLE = frozenset({"revolute", "continuous", "prismatic"})
KINDS = MOVABLE | {"fixed", "floating", "planar"}

Vector = tuple[float, float, float]
Quaternion = tuple[float, float, float, float]  # x, y, z, w


class UrdfError(RocomaError, ValueError):
    """A URDF that cannot be used; the message names the file and the problem."""


class Transform(NamedTuple):
    """A joint's parent link -> child link transform (foxglove.FrameTransform's parts)."""
    parent: str
    child: str
    translation: Vector
    rotation: Quaternion


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str  # one of KINDS
    parent: str
    child: str
    xyz: Vector
    rotation: Quaternion  # of the origin's rpy
    axis: Vector  # unit length

    def transform(self, position: float) -> Transform:
        """At ``position`` (rad, or m for prismatic; not finite: at the origin)."""
        if self.kind not in MOVABLE or not math.isfinite(position):
            return Transform(self.parent, self.child, self.xyz, self.rotation)
        if self.kind == "prismatic":
            offset = _rotate(self.rotation, tuple(a * position for a in self.axis))
            return Transform(self.parent, self.child,
                             (self.xyz[0] + offset[0], self.xyz[1] + offset[1],
                              self.xyz[2] + offset[2]), self.rotation)
        s = math.sin(position / 2)
        turn = (self.axis[0] * s, self.axis[1] * s, self.axis[2] * s, math.cos(position / 2))
        return Transform(self.parent, self.child, self.xyz, _multiply(self.rotation, turn))


@dataclass(frozen=True)
class Robot:
    """A URDF read (``text`` as in the file: what Foxglove is sent) and its joints."""
    name: str
    source: str
    text: str
    links: tuple[str, ...]
    joints: tuple[Joint, ...]

    @property
    def movable(self) -> tuple[str, ...]:
        """The joints a drive can move, in the file's order."""
        return tuple(j.name for j in self.joints if j.kind in MOVABLE)

    def transforms(self, positions: Mapping[str, float]) -> list[Transform]:
        """Every joint's transform; a joint ``positions`` does not name is at its origin."""
        return [j.transform(positions.get(j.name, 0.0)) for j in self.joints]

    def as_json(self) -> dict[str, Any]:
        """The robot as read, in plain values: what the recording's writer process is
        handed, so it takes this reading instead of parsing the file again."""
        return {"name": self.name, "source": self.source, "text": self.text,
                "links": list(self.links),
                "joints": [[j.name, j.kind, j.parent, j.child, list(j.xyz), list(j.rotation),
                            list(j.axis)] for j in self.joints]}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Robot:
        """A robot from ``as_json`` (read by this module before: not checked again)."""
        joints = tuple(Joint(name, kind, parent, child, (xyz[0], xyz[1], xyz[2]),
                             (q[0], q[1], q[2], q[3]), (axis[0], axis[1], axis[2]))
                       for name, kind, parent, child, xyz, q, axis in data["joints"])
        return cls(data["name"], data["source"], data["text"], tuple(data["links"]), joints)


def read_urdf(path: str | Path) -> Robot:
    """The URDF file at ``path``; UrdfError (one line) when it cannot be used.

    Only a regular file is read: opening a FIFO waits for a writer and reading a device
    may never end, so a ``urdf:`` naming one would hang ``check-config`` and ``run``. It is
    looked at before it is opened (opening some devices does something), opened without
    waiting (a FIFO swapped in meanwhile opens at once) and looked at again once open."""
    try:
        raw = read_regular(path, MAX_URDF_BYTES + 1)
    except NotRegularFile as exc:
        raise UrdfError(f"{path}: {exc.strerror}; a URDF is read from a file") from None
    except OSError as exc:
        raise UrdfError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return parse_urdf(raw, str(path))


def parse_urdf(raw: bytes, source: str) -> Robot:
    """A URDF from its bytes; ``source`` names it in the errors."""
    if len(raw) > MAX_URDF_BYTES:
        raise UrdfError(f"{source}: larger than {MAX_URDF_BYTES} bytes; not a URDF")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UrdfError(f"{source}: not UTF-8 text ({exc.reason} at byte {exc.start})") \
            from None
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        raise UrdfError(f"{source}: has a DOCTYPE or ENTITY declaration; refused (a URDF "
                        "needs none, and entities can expand without bound or read files)")
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as exc:
        raise UrdfError(f"{source}: not XML ({exc})") from None
    try:
        links, joints = _tree(root)
    except ValueError as exc:
        raise UrdfError(f"{source}: {exc}") from None
    return Robot(root.get("name", ""), source, text, links, joints)


def _tree(root: ET.Element) -> tuple[tuple[str, ...], tuple[Joint, ...]]:
    """The links and joints; ValueError says what is wrong, where. Each check is a look-up
    by name, so the work grows with the file, not with its square (a snake of 14,000
    links took 16 s when every joint was compared with every joint before it)."""
    if root.tag != "robot":
        raise ValueError(f"no <robot> root element (found <{root.tag}>)")
    links: dict[str, None] = {}  # a set that keeps the file's order
    for i, link in enumerate(root.findall("link")):
        name = link.get("name")
        if not name:
            raise ValueError(f"<link> {i + 1} has no name")
        if name in links:
            raise ValueError(f"two links named {name!r}")
        links[name] = None
    if not links:
        raise ValueError(f"robot {root.get('name', '')!r} has no <link>: an empty robot")
    joints: dict[str, Joint] = {}
    parent_joint: dict[str, Joint] = {}  # child link -> the joint that moves it
    children: dict[str, list[str]] = {}  # parent link -> its child links
    for i, element in enumerate(root.findall("joint")):
        joint = _joint(element, i)
        if joint.name in joints:
            raise ValueError(f"two joints named {joint.name!r}")
        for end in (joint.parent, joint.child):
            if end not in links:
                raise ValueError(f"joint {joint.name!r}: no link named {end!r}")
        other = parent_joint.get(joint.child)
        if other is not None:
            raise ValueError(f"link {joint.child!r} is the child of joints {other.name!r} "
                             f"and {joint.name!r}; a URDF is a tree")
        joints[joint.name] = parent_joint[joint.child] = joint
        children.setdefault(joint.parent, []).append(joint.child)
    roots = [name for name in links if name not in parent_joint]
    if len(roots) != 1:
        raise ValueError("no root link: its joints make a loop" if not roots else
                         f"{len(roots)} root links ({', '.join(roots)}); a URDF is one tree")
    # every link has one parent at most: one not under the root is on a loop of its own
    reached, todo = {roots[0]}, [roots[0]]
    while todo:
        for child in children.get(todo.pop(), ()):
            reached.add(child)
            todo.append(child)
    astray = [name for name in links if name not in reached]
    if astray:
        raise ValueError(f"links {', '.join(astray)} are not under the root link "
                         f"{roots[0]!r}: their joints make a loop")
    return tuple(links), tuple(joints.values())


def _joint(element: ET.Element, i: int) -> Joint:
    name, kind = element.get("name"), element.get("type")
    if not name:
        raise ValueError(f"<joint> {i + 1} has no name")
    where = f"joint {name!r}"
    if kind not in KINDS:
        raise ValueError(f"{where}: type {kind!r} is none of {', '.join(sorted(KINDS))}")
    ends = []
    for tag in ("parent", "child"):
        end = element.find(tag)
        link = end.get("link") if end is not None else None
        if not link:
            raise ValueError(f"{where}: no <{tag} link=...>")
        ends.append(link)
    origin = element.find("origin")
    xyz = _vector(origin, "xyz", where)
    roll, pitch, yaw = _vector(origin, "rpy", where)
    axis = _vector(element.find("axis"), "xyz", f"{where}: <axis>", (1.0, 0.0, 0.0))
    length = math.sqrt(sum(a * a for a in axis))
    if kind in MOVABLE and length < 1e-9:
        raise ValueError(f"{where}: <axis xyz> is zero; a {kind} joint moves along it")
    unit = (axis[0] / length, axis[1] / length, axis[2] / length) if length else axis
    return Joint(name, kind, ends[0], ends[1], xyz, _from_rpy(roll, pitch, yaw), unit)


def _vector(element: ET.Element | None, key: str, where: str,
            default: Vector = (0.0, 0.0, 0.0)) -> Vector:
    """Three finite numbers, or ``default`` when the element or attribute is absent."""
    text = element.get(key) if element is not None else None
    if text is None:
        return default
    try:
        x, y, z = (float(v) for v in text.split())
    except ValueError:
        raise ValueError(f"{where}: {key}={text!r} is not three numbers") from None
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise ValueError(f"{where}: {key}={text!r} is not finite")
    return x, y, z


def _from_rpy(roll: float, pitch: float, yaw: float) -> Quaternion:
    """URDF's rpy: roll about X, then pitch about Y, then yaw about Z, all fixed axes."""
    sr, cr = math.sin(roll / 2), math.cos(roll / 2)
    sp, cp = math.sin(pitch / 2), math.cos(pitch / 2)
    sy, cy = math.sin(yaw / 2), math.cos(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def _multiply(a: Quaternion, b: Quaternion) -> Quaternion:
    """``a`` then ``b`` in ``a``'s frame (the Hamilton product a * b)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def _rotate(q: Quaternion, v: tuple[float, ...]) -> Vector:
    """``v`` rotated by ``q`` (q * v * q^-1)."""
    x, y, z, _ = _multiply(_multiply(q, (v[0], v[1], v[2], 0.0)), (-q[0], -q[1], -q[2], q[3]))
    return x, y, z
