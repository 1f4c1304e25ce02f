"""A ROS 2 node on a Zenoh session, as rmw_zenoh makes one: a node token, and per topic a Zenoh publisher
on the topic's key with its publisher token, each sample with its attachment (``ros2_wire``). With the
``bridge`` key format, samples go on the topic's name alone and carry no attachment or token (a DDS
bridge announces its topics in its own admin space)."""

from __future__ import annotations

import hashlib
import itertools
import threading
import time

from .ros2_wire import DEFAULT_QOS, LATCHED_DEPTH, LATCHED_QOS, encode_attachment, node_token, publisher_token, topic_key, typestore

_NODE_IDS = itertools.count(1)


class Ros2Node:
    """Publishers of ROS 2 messages on ``session``; ``publish(topic, cdr)`` puts serialised messages,
    ``publish_message(topic, msg)`` serialises rosbags messages first."""

    def __init__(self, session, name: str, *, key_format: str = "rmw_zenoh", domain_id: int = 0, store=None, block: bool = False):
        self.session, self.name, self.key_format, self.domain_id = session, name, key_format, domain_id
        self.block = block  # wait for the network when its buffers are full (a replay: nothing lost) instead of dropping the sample
        self.store = store if store is not None else typestore()
        self.session_id = str(session.zid())
        self.node_id = next(_NODE_IDS)
        self._entities = itertools.count(self.node_id * 1000 + 1)
        self._publishers: dict[str, tuple] = {}  # topic -> (zenoh publisher, msgtype, gid, sequence counter)
        self._tokens = []
        self._lock = threading.Lock()
        if key_format == "rmw_zenoh":
            self._tokens.append(session.liveliness().declare_token(node_token(domain_id, self.session_id, self.node_id, name)))

    def advertise(self, topic: str, msgtype: str, *, latched: bool = False) -> None:
        """Declare a publisher of ``msgtype`` on ``topic`` (and its liveliness token), once per topic. ``latched``:
        TRANSIENT_LOCAL durability, as ``/tf_static``: the last ``LATCHED_DEPTH`` messages are kept for subscribers
        that join later (Zenoh's advanced publisher with a cache and publisher detection, as rmw_zenoh does)."""
        with self._lock:
            if topic in self._publishers:
                return
            type_hash = self.store.hash_rihs01(msgtype) if self.key_format == "rmw_zenoh" else ""
            key = topic_key(topic, key_format=self.key_format, domain_id=self.domain_id, msgtype=msgtype, type_hash=type_hash)
            entity = next(self._entities)
            if self.key_format == "rmw_zenoh":
                token = publisher_token(self.domain_id, self.session_id, self.node_id, entity, self.name, topic, msgtype, type_hash,
                                        qos=LATCHED_QOS if latched else DEFAULT_QOS)
                self._tokens.append(self.session.liveliness().declare_token(token))
            gid = hashlib.blake2b(f"{self.session_id}/{self.node_id}/{entity}".encode(), digest_size=16).digest()
            from .session import zenoh_module

            zenoh = zenoh_module()
            congestion = zenoh.CongestionControl.BLOCK if self.block else zenoh.CongestionControl.DROP
            if latched:
                # samples sequenced by number (miss detection), so the session needs no timestamping
                publisher = zenoh.ext.declare_advanced_publisher(self.session, key, congestion_control=congestion, publisher_detection=True,
                                                                 cache=zenoh.ext.CacheConfig(LATCHED_DEPTH),
                                                                 sample_miss_detection=zenoh.ext.MissDetectionConfig())
            else:
                publisher = self.session.declare_publisher(key, congestion_control=congestion)
            self._publishers[topic] = (publisher, msgtype, gid, itertools.count(1))

    def wait_for_subscribers(self, timeout: float, settle: float = 0.3) -> list[str]:
        """Wait until a subscriber matches one of the publishers and no further one has matched for ``settle``
        seconds, ``timeout`` seconds at most; returns the topics with subscribers."""
        end = time.monotonic() + timeout
        matched, since = [], time.monotonic()
        while time.monotonic() < end:
            now_matched = [t for t, (publisher, *_) in self._publishers.items()
                           if hasattr(publisher, "matching_status") and publisher.matching_status.matching]
            if now_matched != matched:
                matched, since = now_matched, time.monotonic()
            elif matched and time.monotonic() - since >= settle:
                break
            time.sleep(0.02)
        return matched

    def publish(self, topic: str, cdr: bytes, msgtype: str | None = None) -> None:
        """Put one serialised message on ``topic`` (advertised on first use when ``msgtype`` is given)."""
        if topic not in self._publishers:
            self.advertise(topic, msgtype)
        publisher, _, gid, sequence = self._publishers[topic]
        if self.key_format == "rmw_zenoh":
            publisher.put(cdr, attachment=encode_attachment(next(sequence), time.time_ns(), gid))
        else:
            publisher.put(cdr)

    def publish_message(self, topic: str, msg) -> None:
        """Serialise a rosbags message (CDR, little-endian) and put it on ``topic``."""
        self.publish(topic, bytes(self.store.serialize_cdr(msg, msg.__msgtype__)), msg.__msgtype__)

    def close(self) -> None:
        """Undeclare the publishers and tokens (``ros2 topic list`` forgets them)."""
        with self._lock:
            for publisher, *_ in self._publishers.values():
                publisher.undeclare()
            for token in self._tokens:
                token.undeclare()
            self._publishers.clear()
            self._tokens.clear()
