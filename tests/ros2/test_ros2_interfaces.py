"""rocoma_can/ros2/interfaces.py, graph.py: the ROS 2 node's contract with rmw_zenoh, without a
session: RIHS01 type hashes against the values published with the ROS packages (the generated type
descriptions of the Jazzy builds: sensor_msgs, std_msgs, std_srvs, service_msgs, rcl_interfaces,
diagnostic_msgs, controller_manager_msgs), the key expressions, liveliness tokens and QoS text
against ros2/rmw_zenoh's docs/design.md examples, and the attachment."""
from __future__ import annotations

import pytest

from rocoma_can.ros2.graph import (
    NODE,
    PUBLISHER,
    SERVICE_CLIENT,
    SERVICE_SERVER,
    SUBSCRIPTION,
    NodeName,
    Qos,
    attachment,
    qualified,
    read_attachment,
    topic_key,
)
from rocoma_can.ros2.interfaces import (
    DIAGNOSTIC_ARRAY,
    DISTROS,
    JOINT_STATE,
    LIST_CONTROLLERS,
    LOG,
    STRING,
    SWITCH_CONTROLLER,
    TRIGGER,
    InterfaceError,
    Interfaces,
    dds_type_name,
)

#: published with the packages (their generated type descriptions), none computed here
PUBLISHED = {
    JOINT_STATE: "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    STRING: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    TRIGGER: "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f",
    LOG: "RIHS01_e28ce254ca8abc06abf92773b74602cdbf116ed34fbaf294fb9f81da9f318eac",
    DIAGNOSTIC_ARRAY:
        "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
    # its char[16] client_gid is uint8[16] to rosidl: rosbags alone hashes it wrongly
    "service_msgs/msg/ServiceEventInfo":
        "RIHS01_41bcbbe07a75c9b52bc96bfd5c24d7f0fc0a08c0cb7921b3373c5732345a6f45",
}
#: controller_manager_msgs, published with ros2_control's builds, by the release whose
#: definitions they hash
PUBLISHED_CONTROL = {
    ("4.0", LIST_CONTROLLERS):
        "RIHS01_b51c7f13c7e9652da7e5b7a66485b62215835723754e6f8ddfdb99141c1c586d",
    ("4.0", "controller_manager_msgs/msg/ControllerState"):
        "RIHS01_38fe2e791900d2bb9e35be49861e88943f11de93e2ec52eb16af7b037116dcd8",
    ("4.0", SWITCH_CONTROLLER):
        "RIHS01_86024c2b173a21e59e6dd474331f1f6380449f806b7466bc8289c79a7baffbe7",
    ("4.13", SWITCH_CONTROLLER):
        "RIHS01_86024c2b173a21e59e6dd474331f1f6380449f806b7466bc8289c79a7baffbe7",
    ("4.28", LIST_CONTROLLERS):
        "RIHS01_4f8e36bb1fa5afdeba45c2d56ae6a2097b1493a253f961dd6290c085033bd189",
    ("4.28", "controller_manager_msgs/msg/ControllerState"):
        "RIHS01_9a8780ab9814b6032978a07c6c7033cf1a7894ac8d948a6fb72afea07b04cc83",
    ("4.28", "controller_manager_msgs/msg/ChainConnection"):
        "RIHS01_2daecd1da4b171f48b291c79747657a651eb1ab8821b68e38b1c88c736bba91c",
}
STRING_HASH = PUBLISHED[STRING]


@pytest.mark.parametrize("distro", DISTROS)
@pytest.mark.parametrize("name", sorted(PUBLISHED))
def test_the_type_hashes_are_the_published_ones(distro, name):
    assert Interfaces(distro).hash(name) == PUBLISHED[name]


@pytest.mark.parametrize("release,name", sorted(PUBLISHED_CONTROL))
def test_the_controller_manager_hashes_are_the_published_ones(release, name):
    assert Interfaces("jazzy", release).hash(name) == PUBLISHED_CONTROL[(release, name)]


def test_rosbags_alone_hashes_the_service_event_info_wrongly():
    """Why the char fields are rosidl's uint8 here (the check above would pass either way
    if rosbags were right)."""
    from rosbags.typesys import Stores, get_typestore
    raw = get_typestore(Stores.ROS2_JAZZY).hash_rihs01("service_msgs/msg/ServiceEventInfo")
    assert raw != PUBLISHED["service_msgs/msg/ServiceEventInfo"]


def test_an_unknown_distro_or_release_is_said():
    with pytest.raises(InterfaceError, match="humble.*served: jazzy, kilted"):
        Interfaces("humble")
    with pytest.raises(InterfaceError, match="'9.9'.*known: 4.0, 4.13, 4.28"):
        Interfaces("jazzy", "9.9")


def test_key_expressions_as_the_design_doc_gives_them():
    string = dds_type_name(STRING)
    assert string == "std_msgs::msg::dds_::String_"
    assert topic_key(0, "/chatter", string, STRING_HASH) == f"0/chatter/{string}/{STRING_HASH}"
    assert topic_key(0, qualified("/robot1", "chatter"), string, STRING_HASH) \
        == f"0/robot1/chatter/{string}/{STRING_HASH}"
    assert topic_key(2, "/add_two_ints", dds_type_name("example_interfaces/srv/AddTwoInts"),
                     "RIHS01_e118") == \
        "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118"
    assert qualified("/robot1", "/joint_states") == "/joint_states"  # absolute stays
    assert qualified("/", "rocoma/estop") == "/rocoma/estop"


def test_liveliness_tokens_as_the_design_doc_gives_them():
    """docs/design.md's demo_nodes_cpp examples, token for token."""
    zid, qos = "aac3178e146ba6f1fc6e6a4085e77f21", Qos(depth=10)
    listener = NodeName(2, zid, "listener")
    assert listener.token() == f"@ros2_lv/2/{zid}/0/0/{NODE}/%/%/listener"
    assert listener.entity_token(10, SUBSCRIPTION, "/chatter", dds_type_name(STRING),
                                 STRING_HASH, qos) == (
        f"@ros2_lv/2/{zid}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,")
    talker = NodeName(2, "8b20917502ee955ac4476e0266340d5c", "talker")
    assert talker.entity_token(10, PUBLISHER, "/chatter", dds_type_name(STRING), STRING_HASH,
                               Qos(depth=7)).endswith(f"/MP/%/%/talker/%chatter/"
                                                      f"std_msgs::msg::dds_::String_/"
                                                      f"{STRING_HASH}/::,7:,:,:,,")
    server = NodeName(2, "f9980ee0495eaafb3e38f0d19e2eae12", "add_two_ints_server")
    add = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
    assert server.entity_token(10, SERVICE_SERVER, "/add_two_ints",
                               "example_interfaces::srv::dds_::AddTwoInts_", add, qos) == (
        "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/"
        f"%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{add}/::,10:,:,:,,")
    assert SERVICE_CLIENT == "SC"
    # a namespace: its '/' as '%', as the fully qualified topic name's
    ns = NodeName(0, zid, "rocoma", "/robot1")
    assert ns.token().endswith("/NN/%/%robot1/rocoma")
    assert "/rocoma/%robot1%joint_states/" in ns.entity_token(
        1, PUBLISHER, "/robot1/joint_states", dds_type_name(JOINT_STATE), "RIHS01_x")


def test_qos_text_leaves_rmw_zenohs_defaults_empty():
    assert Qos(depth=42).text() == "::,:,:,:,,"  # every field the default
    assert Qos(depth=1000, lifespan=10.0).text() == "::,1000:,:10,0:,,"  # /rosout's
    assert Qos(reliability=2, durability=1, history=2, depth=5).text() == "2:1:2,5:,:,:,,"


def test_the_attachment_is_33_bytes_and_reads_back():
    gid = bytes(range(16))
    raw = attachment(7, gid, stamp_ns=1_700_000_000_123_456_789)
    assert len(raw) == 33
    assert raw[:8] == (7).to_bytes(8, "little") and raw[16] == 16 and raw[17:] == gid
    back = read_attachment(raw)
    assert back is not None and (back.sequence, back.stamp_ns, back.gid) == (
        7, 1_700_000_000_123_456_789, gid)
    assert read_attachment(raw[:20]) is None and read_attachment(None) is None
