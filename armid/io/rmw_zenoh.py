"""ROS 2 over Zenoh as rmw_zenoh defines it: type hashes, key expressions, attachments, liveliness.

A ROS 2 node on rmw_zenoh (``rmw_zenoh_cpp``, its ``docs/design.md``) is a Zenoh session; armid
speaks the same wire without ROS installed:

- **data**: a publication is a put of the message's CDR (:mod:`armid.io.ros2_cdr`) on
  ``<domain>/<topic without its leading slash>/<dds type>/<type hash>``, e.g.
  ``0/armid/puma560/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13e...260e``;
- **type hash**: REP-2016's ``RIHS01_`` + SHA-256 of the type description (the type and every
  type it uses, fields only: no comments, constants or defaults) as JSON (:func:`type_hash`);
- **attachment**: every put carries the publisher's sequence number, its source time stamp and
  its GID, without which rmw_zenoh drops the sample. The layout is rmw_zenoh_cpp's since its
  "Change serialization format in attachment_helpers.cpp" (ros2/rmw_zenoh#605; Jazzy 0.2.4,
  Kilted, Rolling): zenoh-ext serialization of ``int64`` sequence number, ``int64`` source time
  stamp (ns since the epoch) and the 16-byte GID as a sequence, i.e. 33 bytes little-endian:
  ``<q sequence><q timestamp><u8 16><16 bytes gid>`` (:func:`attachment`). Jazzy 0.2.0 to 0.2.3
  wrote each value after its name (``"sequence_number"``, ...), which this layout does not read;
- **graph**: liveliness tokens ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>``
  for a node and ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP|MS/<enclave>/<namespace>/<node>/<topic>/<dds type>/<type hash>/<qos>``
  for its publishers and subscriptions (``/`` in a name written ``%``; an empty namespace or
  enclave ``%``): what ``ros2 topic list`` and ``ros2 node list`` read.

armid's session here is a Zenoh client of the ROS 2 router (``rmw_zenohd``, by default
``tcp/localhost:7447``), multicast scouting off: every message passes the router, as a remote
node's do.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
import os
import re
import struct
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from armid.schema.errors import OptionError

from .ros2_cdr import typestore

ADMIN_SPACE = "@ros2_lv"
DEFAULT_ROUTER = "tcp/localhost:7447"
DEFAULT_QOS = "::,10:,:,:,,"
"""rmw_zenoh's QoS in a token, each field left empty where it is the default profile's:
reliable, volatile, keep last 10, no deadline, lifespan or liveliness lease."""
GID_BYTES = 16
ATTACHMENT = struct.Struct("<qqB16s")

# REP-2016 field type ids (type_description_interfaces/msg/FieldType); a .msg ``char`` is an
# IDL uint8 and a .msg ``byte`` an IDL octet (rosidl_adapter), so they hash as those
_TYPE_IDS = {"int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8, "uint64": 9, "float32": 10,
             "float64": 11, "float128": 12, "char": 3, "bool": 15, "byte": 16, "string": 17, "wstring": 18}
_NESTED, _BOUNDED_STRING, _BOUNDED_WSTRING = 1, 21, 22
_ARRAY, _BOUNDED_SEQUENCE, _SEQUENCE = 48, 96, 144


def _field_type(desc: Any) -> dict[str, Any]:
    """One field's ``FieldType`` from a typestore field description (Nodetype, detail)."""
    kind, detail = int(desc[0]), desc[1]
    offset = capacity = 0
    if kind in (3, 4):  # ARRAY, SEQUENCE: (element description, length or bound)
        (kind, detail), length = detail
        kind = int(kind)
        offset, capacity = (_ARRAY, length) if desc[0] == 3 else ((_BOUNDED_SEQUENCE, length) if length else (_SEQUENCE, 0))
    if kind == 2:  # NAME: a nested type
        return {"type_id": offset + _NESTED, "capacity": capacity, "string_capacity": 0, "nested_type_name": detail}
    base, bound = detail
    if base in ("string", "wstring") and bound:
        tid = _BOUNDED_STRING if base == "string" else _BOUNDED_WSTRING
        return {"type_id": offset + tid, "capacity": capacity, "string_capacity": bound, "nested_type_name": ""}
    return {"type_id": offset + _TYPE_IDS[base], "capacity": capacity, "string_capacity": 0, "nested_type_name": ""}


def type_description(kind: str, store: Any = None) -> dict[str, Any]:
    """REP-2016's hashed type description of ``kind`` (``pkg/msg/Name``): the type's fields and,
    sorted by name, every type it uses; an empty type holds one ``uint8`` as rosidl gives it."""
    fielddefs = (store or typestore()).fielddefs
    seen: dict[str, dict[str, Any]] = {}

    def describe(name: str) -> dict[str, Any]:
        fields = fielddefs[name][1] or [("structure_needs_at_least_one_member", (1, ("uint8", 0)))]
        described: list[dict[str, Any]] = [{"name": f, "type": _field_type(d)} for f, d in fields]
        for f in described:
            nested = f["type"]["nested_type_name"]
            if nested and nested not in seen:
                seen[nested] = {}
                seen[nested] = describe(nested)
        return {"type_name": name, "fields": described}

    top = describe(kind)
    return {"type_description": top, "referenced_type_descriptions": [seen[n] for n in sorted(seen) if n != kind]}


def type_hash(kind: str, store: Any = None) -> str:
    """REP-2016's ``RIHS01_<sha256>`` of ``kind`` (in ``store``, by default armid's): the JSON of
    :func:`type_description` as rosidl writes it (``", "`` and ``": "`` separators, keys in their order)."""
    return _hash_of(kind) if store is None else _hash(kind, store)


@functools.lru_cache(maxsize=64)
def _hash_of(kind: str) -> str:
    return _hash(kind, None)


def _hash(kind: str, store: Any) -> str:
    text = json.dumps(type_description(kind, store), separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()


def dds_type_name(kind: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (the key's type)."""
    package, sub, name = kind.split("/")
    return f"{package}::{sub}::dds_::{name}_"


def mangle(name: str) -> str:
    """A name inside one key chunk: ``/`` as ``%``; empty or ``/`` is ``%``."""
    return "%" if name in ("", "/") else name.replace("/", "%")


_ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def ros_name(text: str) -> str:
    """``text`` as one token of a ROS name: letters, digits and ``_``, not starting with a digit."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", text) or "_"
    return f"_{token}" if token[0].isdigit() else token


def check_topic(topic: str) -> str:
    """A fully qualified ROS 2 topic name (``/a/b``), or :class:`OptionError`."""
    if not _ROS_NAME.match(topic):
        raise OptionError("--ros2-source", f"{topic!r} is not a ROS 2 topic name (/name/of_tokens: letters, digits, _)")
    return topic


def data_key(domain: int, topic: str, kind: str, hash_: str | None = None) -> str:
    """The key expression of ``topic``'s data (``hash_="*"``: any type hash)."""
    return f"{domain}/{topic.strip('/')}/{dds_type_name(kind)}/{hash_ or type_hash(kind)}"


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """The attachment of one publication (module docstring: rmw_zenoh's layout since #605)."""
    return ATTACHMENT.pack(sequence, stamp_ns, GID_BYTES, gid)


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source time stamp in ns, GID) of an attachment; ``ValueError`` when it
    is not one in this layout."""
    if len(data) != ATTACHMENT.size or data[16] != GID_BYTES:
        raise ValueError(f"not an rmw_zenoh attachment: {len(data)} bytes (expected {ATTACHMENT.size}, the GID's length 16 at byte 16)")
    sequence, stamp, _, gid = ATTACHMENT.unpack(data)
    return int(sequence), int(stamp), bytes(gid)


def domain_id(value: int | None) -> int:
    """``value``, else ``ROS_DOMAIN_ID``, else 0 (ROS 2's order)."""
    if value is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip()
        try:
            value = int(text) if text else 0
        except ValueError:
            raise OptionError("ROS_DOMAIN_ID", f"{text!r} is not a whole number") from None
    if not 0 <= value <= 232:
        raise OptionError("--ros2-domain", f"{value} is not a ROS 2 domain id (0 to 232)")
    return value


def open_session(router: str) -> Any:
    """A Zenoh client of the ROS 2 router at ``router``, multicast scouting off; an endpoint
    that cannot be used is :class:`OptionError` (exit 2)."""
    import zenoh

    config = zenoh.Config()
    try:
        config.insert_json5("mode", '"client"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps([router]))
        config.insert_json5("connect/timeout_ms", "5000")
        return zenoh.open(config)
    except Exception as err:  # zenoh's ZError: a malformed endpoint, no router there
        text = re.sub(r"\s+", " ", str(err))[:200]
        raise OptionError("--ros2-router", f"cannot reach a ROS 2 Zenoh router at {router} ({text})") from None


_IDS = itertools.count(1)  # node and entity ids, unique in this process (rmw_zenoh: per context)


@dataclass(frozen=True)
class Endpoint:
    """A publisher or subscription as the graph sees it."""

    topic: str
    kind: str
    role: str  # "MP" publisher, "MS" subscription
    entity_id: int


class Ros2Node:
    """A ROS 2 node on an open Zenoh session: its liveliness token, publishers and subscriptions."""

    def __init__(self, session: Any, name: str, domain: int, namespace: str = "/") -> None:
        self.session = session
        self.name = ros_name(name)
        self.domain = domain
        self.namespace = namespace
        self.zid = str(session.info.zid())
        self.node_id = next(_IDS)
        self._lock = threading.Lock()
        self._entities: list[Any] = [session.liveliness().declare_token(self.token())]

    def _prefix(self, entity_id: int, role: str) -> str:
        return (f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{role}/%/"
                f"{mangle(self.namespace)}/{self.name}")

    def token(self) -> str:
        """The node's liveliness key expression (``NN``)."""
        return self._prefix(self.node_id, "NN")

    def endpoint_token(self, e: Endpoint) -> str:
        """A publisher's (``MP``) or subscription's (``MS``) liveliness key expression."""
        return f"{self._prefix(e.entity_id, e.role)}/{mangle(e.topic)}/{dds_type_name(e.kind)}/{type_hash(e.kind)}/{DEFAULT_QOS}"

    def publisher(self, topic: str, kind: str) -> Ros2Publisher:
        """A publisher of ``kind`` on ``topic``, announced on the graph."""
        e = Endpoint(topic, kind, "MP", next(_IDS))
        pub = Ros2Publisher(self.session, data_key(self.domain, topic, kind), self.session.liveliness().declare_token(self.endpoint_token(e)))
        with self._lock:
            self._entities.append(pub)
        return pub

    def subscribe(self, topic: str, kind: str, callback: Callable[[bytes, bytes | None], None]) -> Endpoint:
        """Call ``callback(cdr, attachment)`` for each message of ``kind`` on ``topic`` (from
        Zenoh's thread: queue, never block), whatever its publisher's type hash (the CDR is
        checked where it is decoded); announced on the graph."""

        def on_sample(sample: Any) -> None:
            att = sample.attachment
            callback(sample.payload.to_bytes(), None if att is None else att.to_bytes())

        e = Endpoint(topic, kind, "MS", next(_IDS))
        sub = self.session.declare_subscriber(data_key(self.domain, topic, kind, "*"), on_sample)
        token = self.session.liveliness().declare_token(self.endpoint_token(e))
        with self._lock:
            self._entities += [sub, token]
        return e

    def close(self) -> None:
        """Undeclare everything (safe twice); the session stays the caller's."""
        with self._lock:
            entities, self._entities = self._entities, []
        for entity in reversed(entities):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                pass


class Ros2Publisher:
    """One ROS 2 publisher: a Zenoh publisher on its data key and its liveliness token."""

    def __init__(self, session: Any, key: str, token: Any) -> None:
        import zenoh

        self.key = key
        self.gid = uuid.uuid4().bytes
        self.sequence = 0
        self._token = token
        self._encoding = zenoh.Encoding("application/cdr")
        # a slow or absent subscriber drops messages rather than holding up the process that publishes
        self._pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)

    def put(self, cdr: bytes) -> None:
        """Publish one CDR message with its attachment (the next sequence number, now)."""
        self.sequence += 1
        self._pub.put(cdr, encoding=self._encoding, attachment=attachment(self.sequence, time.time_ns(), self.gid))

    def undeclare(self) -> None:
        for entity in (self._token, self._pub):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                pass
