"""The ``ros2:`` config section and the ``--ros2`` family of command-line options
(docs/ros2.md); both go through ``parse_ros2``, so a flag is checked as the section is::

    ros2:
      node: rocoma               # the node's name
      namespace: ""              # e.g. /robot1
      domain_id: 0               # ROS_DOMAIN_ID (default: that variable, else 0)
      distro: jazzy              # jazzy or kilted: the type hashes served
      ros2_control: null         # controller_manager_msgs of this ros2_control release
                                 # (4.0, 4.13, 4.28; null: the distro's current)
      mode: client               # a Zenoh client of the router, as rmw_zenoh's nodes reach it
      connect: [tcp/localhost:7447]
      joint_states_rate: 100     # Hz
      controller_manager: controller_manager  # its services' prefix (ros2 control -c NAME)
      allow_commands: false      # clear, recover, switch_controller from ROS 2
      required: true             # no router at start-up: an error (false: a warning)
"""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from typing import Any

from ..fleet.config import known_section
from ..inputs import NAME_TOKEN
from .interfaces import DISTROS, ROS2_CONTROL

DEFAULT_ROUTER = "tcp/localhost:7447"
_KEYS = {"node", "namespace", "domain_id", "distro", "ros2_control", "mode", "connect",
         "joint_states_rate", "controller_manager", "allow_commands", "required"}
#: rmw_zenoh, as DDS, partitions by domain id; ROS 2 accepts 0..232 on Linux
MAX_DOMAIN_ID = 232


def default_domain_id() -> int:
    """ROS_DOMAIN_ID when it is a domain id, else 0 (unset or empty, as rcl has it; any
    other value is refused by ``parse``: see ``domain_id_problem``)."""
    value = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return int(value) if value.isdigit() and int(value) <= MAX_DOMAIN_ID else 0


def domain_id_problem() -> str | None:
    """Why ROS_DOMAIN_ID is no domain id 0..MAX_DOMAIN_ID (None: unset, empty or one).
    rcl refuses a value that is no number; taking one for 0 would put the node in
    another graph, following that graph's commands."""
    raw = os.environ.get("ROS_DOMAIN_ID", "")
    value = raw.strip()
    if not value or (value.isdigit() and int(value) <= MAX_DOMAIN_ID):
        return None
    return (f"ROS_DOMAIN_ID is {raw!r}, not a domain id 0..{MAX_DOMAIN_ID} (set it to one, "
            f"unset it for 0, or name the domain here)")


@dataclass
class Ros2Config:
    node: str = "rocoma"
    namespace: str = "/"
    domain_id: int = field(default_factory=default_domain_id)
    distro: str = "jazzy"
    ros2_control: str | None = None
    mode: str = "client"
    connect: list[str] = field(default_factory=lambda: [DEFAULT_ROUTER])
    joint_states_rate: float = 100.0
    #: where list_controllers and switch_controller are served (``ros2 control -c``): another
    #: name than ros2_control's own controller_manager when one runs in the same graph
    controller_manager: str = "controller_manager"
    allow_commands: bool = False
    required: bool = True


def name_problem(name: Any) -> str | None:
    """Why ``name`` is no ROS 2 node name (None: it is one)."""
    if not isinstance(name, str) or not NAME_TOKEN.fullmatch(name):
        return (f"expected a ROS 2 name (a letter or '_', then letters, digits, '_'), "
                f"got {name!r}")
    return None


def controller_manager_problem(name: Any) -> str | None:
    """Why ``name`` is no controller manager's name, relative (in the node's namespace) or
    absolute: its chunks ROS 2 name tokens (None: it is one)."""
    if isinstance(name, str) and all(NAME_TOKEN.fullmatch(chunk)
                                     for chunk in name.removeprefix("/").split("/")):
        return None
    return f"expected a name such as controller_manager or /arm/controller_manager, got {name!r}"


def namespace_problem(namespace: Any) -> str | None:
    """Why ``namespace`` is no ROS 2 namespace ('' or '/': the root; '/a/b')."""
    if not isinstance(namespace, str):
        return f"expected a namespace such as /robot1, got {namespace!r}"
    parts = namespace.strip("/").split("/") if namespace.strip("/") else []
    if any(not NAME_TOKEN.fullmatch(p) for p in parts) or "//" in namespace:
        return f"expected a namespace such as /robot1, got {namespace!r}"
    return None


def parse_ros2(section: Any, problems: list[str], where: str = "ros2",
               base: Ros2Config | None = None) -> Ros2Config | None:
    """The ``ros2:`` section over ``base`` (None: absent), each problem "ros2.KEY: ..."."""
    if section is None or not known_section(section, _KEYS, where, problems):
        return None
    out = base or Ros2Config()

    def take(key: str, why: str | None) -> None:
        if key in section:
            if why:
                problems.append(f"{where}.{key}: {why}")
            else:
                setattr(out, key, section[key])
    take("node", name_problem(section.get("node")))
    if "namespace" in section:
        why = namespace_problem(section["namespace"])
        if why:
            problems.append(f"{where}.namespace: {why}")
        else:
            out.namespace = "/" + section["namespace"].strip("/")
    domain = section.get("domain_id")
    take("domain_id", None if isinstance(domain, int) and not isinstance(domain, bool)
         and 0 <= domain <= MAX_DOMAIN_ID else f"expected 0..{MAX_DOMAIN_ID}, got {domain!r}")
    env_problem = domain_id_problem()
    if base is None and "domain_id" not in section and env_problem:
        problems.append(f"{where}.domain_id: {env_problem}")
    take("distro", None if section.get("distro") in DISTROS
         else f"expected one of {', '.join(DISTROS)}, got {section.get('distro')!r}")
    control = section.get("ros2_control")
    if isinstance(control, float):  # `ros2_control: 4.28` unquoted: a number to YAML
        control = str(control)
    if "ros2_control" in section:
        if control is None or control in ROS2_CONTROL:
            out.ros2_control = control
        else:
            problems.append(f"{where}.ros2_control: expected one of {', '.join(ROS2_CONTROL)} "
                            f"(the ros2_control release whose controller_manager_msgs to "
                            f"serve), got {section['ros2_control']!r}")
    take("mode", None if section.get("mode") in ("client", "peer")
         else f"expected client or peer, got {section.get('mode')!r}")
    if "connect" in section:
        value = section["connect"]
        value = [value] if isinstance(value, str) else value
        if not isinstance(value, list) or not value \
                or not all(isinstance(v, str) and "/" in v for v in value):
            problems.append(f"{where}.connect: expected Zenoh endpoints like "
                            f"{DEFAULT_ROUTER}, got {section['connect']!r}")
        else:
            out.connect = list(value)
    rate = section.get("joint_states_rate")
    take("joint_states_rate", None if isinstance(rate, (int, float))
         and not isinstance(rate, bool) and 0.1 <= rate <= 1000
         else f"expected Hz 0.1..1000, got {rate!r}")
    take("controller_manager", controller_manager_problem(section.get("controller_manager")))
    for key in ("allow_commands", "required"):
        take(key, None if isinstance(section.get(key), bool)
             else f"expected true or false, got {section.get(key)!r}")
    if isinstance(out.joint_states_rate, int):
        out.joint_states_rate = float(out.joint_states_rate)
    return out


def add_ros2_options(p: argparse.ArgumentParser, connect: bool = False) -> None:
    """``--ros2`` and its options, for run and demo alike; ``connect``: add
    ``--zenoh-connect`` here (run has it among its Zenoh options: with --ros2 it names the
    node's router, see ``from_args``)."""
    g = p.add_argument_group("ROS 2 (a node over rmw_zenoh, extra ros2; docs/ros2.md)")
    g.add_argument("--ros2", action="store_true",
                   help="be a ROS 2 node (joint states, diagnostics, services, ros2 control)")
    g.add_argument("--ros-namespace", default=None, metavar="NS", help="the node's namespace")
    g.add_argument("--ros-domain-id", type=int, default=None, metavar="ID",
                   help="ROS domain id (default: ROS_DOMAIN_ID, else 0)")
    g.add_argument("--ros-distro", choices=DISTROS, default=None,
                   help="the distro whose type hashes are served (jazzy)")
    g.add_argument("--ros-allow-commands", action="store_true",
                   help="allow clear, recover and switch_controller from ROS 2")
    if connect:
        g.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT",
                       help=f"the Zenoh router to connect to ({DEFAULT_ROUTER})")


def from_args(args: argparse.Namespace, config: Ros2Config | None,
              problems: list[str]) -> Ros2Config | None:
    """The config's ros2: section with the --ros* flags over it (--ros2, or any of them, turns
    the node on); ``--zenoh-connect`` endpoints are the router's when given."""
    flags: dict[str, Any] = {}
    if args.ros_namespace is not None:
        flags["namespace"] = args.ros_namespace
    if args.ros_domain_id is not None:
        flags["domain_id"] = args.ros_domain_id
    if args.ros_distro is not None:
        flags["distro"] = args.ros_distro
    if args.ros_allow_commands:
        flags["allow_commands"] = True
    if not (args.ros2 or flags or config is not None):
        return None
    if getattr(args, "zenoh_connect", None) and (args.ros2 or flags):
        flags["connect"] = list(args.zenoh_connect)
    return parse_ros2(flags, problems, where="--ros2", base=config)
