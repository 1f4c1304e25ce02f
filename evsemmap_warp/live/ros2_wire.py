"""ROS 2 on Zenoh, as the wire carries it: key expressions, the attachment, liveliness tokens, CDR.

Two key formats (``KEY_FORMATS``):

- ``rmw_zenoh`` (ros2/rmw_zenoh, ``liveliness_utils.cpp``): a topic's samples go to
  ``<domain id>/<topic without its outer slashes>/<DDS type name>/<type hash>``, e.g.
  ``0/os1_cloud_node/points/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198...``; the type hash is the
  type description's RIHS01 hash (``rosbags`` computes it from the message definition). Every sample
  carries an attachment: sequence number (int64), source timestamp (int64, ns since the epoch) and the
  publisher's 16-byte GID, serialized with Zenoh's serializer (``zenoh::ext``: little-endian integers, the
  GID as a sequence, its length 16 as one varint byte, then its bytes: 33 bytes). Every entity announces itself with a liveliness token
  ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>
  [/<topic>/<type>/<hash>/<qos>]``, slashes inside names written ``%``; ``ros2 topic list`` on an
  rmw_zenoh robot lists a topic from its publisher's token.
- ``bridge`` (eclipse-zenoh/zenoh-plugin-ros2dds, the Zenoh bridge of a DDS robot): the topic name alone,
  without its leading slash (prefixed by the bridge's namespace when it has one); no attachment.

Payloads are CDR with its 4-byte encapsulation header in both, which ``rosbags`` reads and writes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from ..config import ConfigError

KEY_FORMATS = ("rmw_zenoh", "bridge")
ADMIN_SPACE = "@ros2_lv"
GID_BYTES = 16
# A liveliness token's QoS field (rmw_zenoh's qos_to_keyexpr: reliability:durability:history,depth:deadline s,ns:
# lifespan s,ns:liveliness,lease s,ns, a value equal to the default left empty): reliable, volatile, keep last 10
DEFAULT_QOS = "::,10:,:,:,,"
# /tf_static's durability: TRANSIENT_LOCAL (1), keep the last LATCHED_DEPTH for subscribers that join later
LATCHED_DEPTH = 100
LATCHED_QOS = f":1:,{LATCHED_DEPTH}:,:,:,,"


def is_latched(topic: str) -> bool:
    """Whether a topic is TRANSIENT_LOCAL by ROS convention: ``/tf_static`` (under any namespace)."""
    return topic.rstrip("/").rsplit("/", 1)[-1] == "tf_static"
ATTACHMENT = struct.Struct("<qqB16s")  # sequence number, source timestamp, GID length (16), GID

# grid_map_msgs for ROS 2 (ANYbotics/grid_map, branches humble / jazzy / rolling): the header moved from the
# info to the map; the ROS 1 text is in terrain/outputs.py.
GRID_MAP_INFO_MSG_ROS2 = """float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""
GRID_MAP_MSG_ROS2 = """std_msgs/Header header
GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""


class WireError(ValueError):
    """A key, attachment or payload that is not what ROS 2 on Zenoh sends; the message says which."""


def typestore():
    """rosbags' ROS 2 (Humble) type store with tf2_msgs and ROS 2's grid_map_msgs registered."""
    try:
        from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    except ImportError:
        raise ConfigError('live mapping decodes ROS messages with the rosbags package: pip install "evsemmap_warp[ros,live]"') from None
    from ..data.log_writer import TF_MESSAGE_DEFINITION

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    if "tf2_msgs/msg/TFMessage" not in store.types:
        types.update(get_types_from_msg(TF_MESSAGE_DEFINITION, "tf2_msgs/msg/TFMessage"))
    types.update(get_types_from_msg(GRID_MAP_INFO_MSG_ROS2, "grid_map_msgs/msg/GridMapInfo"))
    types.update(get_types_from_msg(GRID_MAP_MSG_ROS2, "grid_map_msgs/msg/GridMap"))
    store.register(types)
    return store


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` -> ``sensor_msgs::msg::dds_::PointCloud2_`` (the type in rmw_zenoh's keys)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str:
    """The inverse of ``dds_type_name``; raises WireError for a name of another form."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise WireError(f"{dds_name!r} is not a ROS 2 type name of rmw_zenoh's keys (package::msg::dds_::Name_)")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def topic_key(topic: str, *, key_format: str, domain_id: int = 0, msgtype: str = "", type_hash: str = "") -> str:
    """The key expression ``topic``'s samples are put on; ``msgtype`` / ``type_hash`` ``"*"`` (or empty) for
    a subscription to any type."""
    name = topic.strip("/")
    if not name:
        raise ConfigError(f"topic {topic!r}: a topic needs a name")
    if key_format == "bridge":
        return name
    if key_format != "rmw_zenoh":
        raise ConfigError(f"key format {key_format!r} is unknown; known: {', '.join(KEY_FORMATS)}")
    return f"{domain_id}/{name}/{dds_type_name(msgtype) if msgtype and msgtype != '*' else '*'}/{type_hash or '*'}"


@dataclass(frozen=True)
class SampleKey:
    """What a received sample's key says: its format, topic (with its leading slash) and, for rmw_zenoh, its type."""

    key_format: str
    topic: str
    msgtype: str = ""


def parse_key(key: str, domain_id: int) -> SampleKey:
    """A received key: ``<domain>/<topic>/<type>/<RIHS01_hash>`` is rmw_zenoh's, anything else the bridge's."""
    parts = key.split("/")
    if len(parts) >= 4 and parts[0] == str(domain_id) and parts[-1].startswith("RIHS01_") and "::" in parts[-2]:
        return SampleKey("rmw_zenoh", "/" + "/".join(parts[1:-2]), ros_type_name(parts[-2]))
    return SampleKey("bridge", "/" + key)


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment of one sample (see the module text)."""
    return ATTACHMENT.pack(int(sequence_number), int(source_timestamp_ns), GID_BYTES, bytes(gid)[:GID_BYTES].ljust(GID_BYTES, b"\0"))


def decode_attachment(raw: bytes | None) -> tuple[int, int, bytes] | None:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh attachment; None without one (a bridge's
    sample). Raises WireError for an attachment of another size."""
    if raw is None:
        return None
    if len(raw) != ATTACHMENT.size or raw[16] != GID_BYTES:
        raise WireError(f"an attachment of {len(raw)} bytes, not rmw_zenoh's {ATTACHMENT.size} (sequence number, timestamp, GID)")
    sequence, stamp, _, gid = ATTACHMENT.unpack(raw)
    return sequence, stamp, gid


def mangle(name: str) -> str:
    """A name inside a liveliness token: slashes written ``%`` (an empty namespace ``/`` is ``%``)."""
    return name.replace("/", "%")


def node_token(domain_id: int, session_id: str, node_id: int, node: str, namespace: str = "/") -> str:
    """The liveliness token of a node."""
    return f"{ADMIN_SPACE}/{domain_id}/{session_id}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/{mangle(node)}"


def publisher_token(domain_id: int, session_id: str, node_id: int, entity_id: int, node: str, topic: str, msgtype: str, type_hash: str,
                    namespace: str = "/", qos: str = DEFAULT_QOS) -> str:
    """The liveliness token of a publisher of ``topic`` (type ``msgtype``) on node ``node``."""
    return (f"{ADMIN_SPACE}/{domain_id}/{session_id}/{node_id}/{entity_id}/MP/%/{mangle(namespace)}/{mangle(node)}/"
            f"{mangle(topic)}/{dds_type_name(msgtype)}/{type_hash}/{qos}")


def parse_token(token: str) -> dict | None:
    """A publisher's or subscription's liveliness token as a dict (kind, domain, node, topic, msgtype); None
    for a token of another kind or shape."""
    parts = token.split("/")
    if len(parts) < 13 or parts[0] != ADMIN_SPACE or parts[5] not in ("MP", "MS"):
        return None
    try:
        msgtype = ros_type_name(parts[10])
    except WireError:
        return None
    return {"kind": parts[5], "domain": parts[1], "node": parts[8].replace("%", "/"), "topic": parts[9].replace("%", "/"),
            "msgtype": msgtype, "type_hash": parts[11]}
