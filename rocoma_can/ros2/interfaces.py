"""The ROS 2 interfaces the node speaks, their RIHS01 type hashes and their CDR codec, for
one distro (rosbags: its Jazzy and Kilted type stores carry the standard messages; the
definitions rosbags lacks, std_srvs/Trigger and controller_manager_msgs, are here as the
packages' own .msg/.srv text).

Hashes are rosbags' REP 2016 hash over these definitions, with two things done as rosidl
does them that rosbags does not: a ``char`` field is described as ``uint8`` (rosidl maps the
.msg ``char`` to ``uint8``; rosbags hashes it as ``char``, which made every service hash
wrong: each service's event message holds service_msgs/ServiceEventInfo's ``char[16]``), and
a service is hashed as rosidl describes it, a type of three fields (``request_message``,
``response_message``, ``event_message``) whose event holds the ServiceEventInfo and the
request and response as sequences of at most one. tests/ros2/test_ros2_interfaces.py checks the
results against hashes published with the ROS packages.

controller_manager_msgs changed inside Jazzy: ros2_control 4.13 added
``exported_state_interfaces`` to ControllerState, 4.28 added ``is_async`` and
``update_rate`` and SwitchController's ``message`` (as in Kilted's 5.x). A caller's
ListControllers type hash must equal the node's, so the ros2_control version served is a
setting (ROS2_CONTROL; ``ros2.ros2_control`` in the config).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import RocomaError

DISTROS = ("jazzy", "kilted")
#: the controller_manager_msgs definitions, by the ros2_control release that introduced them
ROS2_CONTROL = ("4.0", "4.13", "4.28")
#: what each distro serves unless told otherwise: its ros2_control's current messages
DEFAULT_ROS2_CONTROL = {"jazzy": "4.28", "kilted": "4.28"}

TRIGGER = "std_srvs/srv/Trigger"
LIST_CONTROLLERS = "controller_manager_msgs/srv/ListControllers"
SWITCH_CONTROLLER = "controller_manager_msgs/srv/SwitchController"
JOINT_STATE = "sensor_msgs/msg/JointState"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
LOG = "rcl_interfaces/msg/Log"
STRING = "std_msgs/msg/String"
#: the messages taken from the distro's type store (with what they reference)
FROM_DISTRO = (JOINT_STATE, DIAGNOSTIC_ARRAY, LOG, STRING,
               "service_msgs/msg/ServiceEventInfo", "builtin_interfaces/msg/Duration")

_CHAIN_CONNECTION = "string name\nstring[] reference_interfaces\n"
_CONTROLLER_STATE = {
    "4.0": ("string name\nstring state\nstring type\nstring[] claimed_interfaces\n"
            "string[] required_command_interfaces\nstring[] required_state_interfaces\n"
            "bool is_chainable\nbool is_chained\nstring[] reference_interfaces\n"
            "controller_manager_msgs/ChainConnection[] chain_connections\n"),
    "4.13": ("string name\nstring state\nstring type\nstring[] claimed_interfaces\n"
             "string[] required_command_interfaces\nstring[] required_state_interfaces\n"
             "bool is_chainable\nbool is_chained\nstring[] exported_state_interfaces\n"
             "string[] reference_interfaces\n"
             "controller_manager_msgs/ChainConnection[] chain_connections\n"),
    "4.28": ("string name\nstring state\nstring type\nbool is_async\nuint16 update_rate\n"
             "string[] claimed_interfaces\nstring[] required_command_interfaces\n"
             "string[] required_state_interfaces\nbool is_chainable\nbool is_chained\n"
             "string[] exported_state_interfaces\nstring[] reference_interfaces\n"
             "controller_manager_msgs/ChainConnection[] chain_connections\n"),
}
_SWITCH_REQUEST = ("string[] activate_controllers\nstring[] deactivate_controllers\n"
                   "int32 strictness\nbool activate_asap\n"
                   "builtin_interfaces/Duration timeout\n")
_SWITCH_RESPONSE = {"4.0": "bool ok\n", "4.13": "bool ok\n",
                    "4.28": "bool ok\nstring message\n"}
#: SwitchController's strictness values (its constants)
BEST_EFFORT, STRICT = 1, 2


class InterfaceError(RocomaError):
    """The ROS 2 interfaces cannot be used (rosbags missing, an unknown distro)."""


@dataclass(frozen=True)
class Service:
    """A service type's request and response message types."""
    name: str

    @property
    def request(self) -> str:
        return f"{self.name}_Request"

    @property
    def response(self) -> str:
        return f"{self.name}_Response"


def dds_type_name(name: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``, the type name of the key expressions."""
    package, kind, base = name.split("/")
    return f"{package}::{kind}::dds_::{base}_"


class Interfaces:
    """Every type the node uses, for ``distro`` and the ``ros2_control`` release's
    controller_manager_msgs: ``hash`` (RIHS01), ``encode`` and ``decode`` (CDR with its
    encapsulation header, little-endian), ``message`` (a message object to encode)."""

    def __init__(self, distro: str = "jazzy", ros2_control: str | None = None) -> None:
        if distro not in DISTROS:
            raise InterfaceError(f"ROS 2 distro {distro!r} is not served (served: "
                                 f"{', '.join(DISTROS)})")
        ros2_control = ros2_control or DEFAULT_ROS2_CONTROL[distro]
        if ros2_control not in ROS2_CONTROL:
            raise InterfaceError(f"ros2_control {ros2_control!r}: its controller_manager_msgs "
                                 f"are not known (known: {', '.join(ROS2_CONTROL)})")
        try:
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            raise InterfaceError("ROS 2 needs rosbags: pip install 'rocoma-can[ros2]'") \
                from None
        self.distro, self.ros2_control = distro, ros2_control
        source = get_typestore(Stores.ROS2_JAZZY if distro == "jazzy" else Stores.ROS2_KILTED)
        self._store = get_typestore(Stores.EMPTY)
        types: dict[str, Any] = {}
        for name in FROM_DISTRO:
            _closure(source.fielddefs, name, types)
        types.update(_msg("controller_manager_msgs/msg/ChainConnection", _CHAIN_CONNECTION))
        types.update(_msg("controller_manager_msgs/msg/ControllerState",
                          _CONTROLLER_STATE[ros2_control]))
        for service, request, response in (
                (TRIGGER, "", "bool success\nstring message\n"),
                (LIST_CONTROLLERS, "",
                 "controller_manager_msgs/ControllerState[] controller\n"),
                (SWITCH_CONTROLLER, _SWITCH_REQUEST, _SWITCH_RESPONSE[ros2_control])):
            types.update(_service(service, request, response))
        self._store.register({name: (consts, [(f, _uint8_chars(d)) for f, d in fields])
                              for name, (consts, fields) in types.items()})
        self._hashes: dict[str, str] = {}

    def hash(self, name: str) -> str:
        """The RIHS01 type hash of a message or service type."""
        if name not in self._hashes:
            self._hashes[name] = self._store.hash_rihs01(name)
        return self._hashes[name]

    def has_field(self, name: str, field: str) -> bool:
        """Whether type ``name`` has ``field`` (the definitions served differ)."""
        return any(f == field for f, _ in self._store.fielddefs[name][1])

    def message(self, type_name: str, /, **fields: Any) -> Any:
        """A message object of type ``type_name`` (rosbags' class) with ``fields``."""
        return self._store.types[type_name](**fields)

    def encode(self, message: Any, name: str) -> bytes:
        return bytes(self._store.serialize_cdr(message, name))

    def decode(self, data: bytes | memoryview, name: str, limit: int | None = None) -> Any:
        """A message of type ``name`` from CDR; ValueError (with why) for bytes that are not
        one, whatever rosbags raised, or that are more than ``limit`` bytes (a peer's
        megabytes would take the interpreter for a good part of a second to decode)."""
        if limit is not None and len(data) > limit:
            raise ValueError(f"a {name} of {len(data)} bytes, more than the {limit} this "
                             "node reads")
        try:
            return self._store.deserialize_cdr(bytes(data), name)
        except Exception as exc:  # rosbags raises struct, index, unicode errors ...
            raise ValueError(f"not a {name} in CDR ({len(data)} bytes): "
                             f"{type(exc).__name__}: {exc}") from None


def _closure(fielddefs: Mapping[str, Any], name: str, out: dict[str, Any]) -> None:
    """``name``'s definition and those of every type it references, from ``fielddefs``."""
    if name in out:
        return
    out[name] = fielddefs[name]
    for _, desc in fielddefs[name][1]:
        nested = _nested(desc)
        if nested is not None:
            _closure(fielddefs, nested, out)


def _nested(desc: Any) -> str | None:
    """The message type a field holds (itself, or in an array or a sequence), else None."""
    from rosbags.interfaces import Nodetype
    kind, rest = desc
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        kind, rest = rest[0]
    return rest if kind == Nodetype.NAME else None


def _uint8_chars(desc: Any) -> Any:
    """A field description with ``char`` as ``uint8``, as rosidl has it (see the module)."""
    from rosbags.interfaces import Nodetype
    kind, rest = desc
    if kind == Nodetype.BASE and rest[0] == "char":
        return (kind, ("uint8", rest[1]))
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return (kind, (_uint8_chars(rest[0]), rest[1]))
    return desc


def _msg(name: str, text: str) -> dict[str, Any]:
    """``name``'s definition parsed from .msg ``text`` (rosbags' parser); a service part's
    name kept as ROS has it (rosbags files ``pkg/srv/X`` as ``pkg/srv/msg/X``)."""
    from rosbags.interfaces import Nodetype
    from rosbags.typesys import get_types_from_msg
    mangled = name.replace("/srv/", "/srv/msg/")

    def unmangle(desc: Any) -> Any:
        kind, rest = desc
        if kind == Nodetype.NAME:
            return (kind, rest.replace("/srv/msg/", "/srv/"))
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            return (kind, (unmangle(rest[0]), rest[1]))
        return desc
    parsed = get_types_from_msg(text, mangled)
    return {key.replace("/srv/msg/", "/srv/"): (consts, [(f, unmangle(d)) for f, d in fields])
            for key, (consts, fields) in parsed.items()}


def _service(name: str, request: str, response: str) -> dict[str, Any]:
    """A service's request, response, event and the service type itself, as rosidl
    describes them (see the module)."""
    from rosbags.interfaces import Nodetype
    srv = Service(name)
    types = {**_msg(srv.request, request), **_msg(srv.response, response)}
    event = f"{name}_Event"
    types[event] = ([], [
        ("info", (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")),
        ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, srv.request), 1))),
        ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, srv.response), 1)))])
    types[name] = ([], [("request_message", (Nodetype.NAME, srv.request)),
                        ("response_message", (Nodetype.NAME, srv.response)),
                        ("event_message", (Nodetype.NAME, event))])
    return types
