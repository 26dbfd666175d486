"""ROS 2 topics over DDS with ``cyclonedds`` (the ``robotd[ros2]`` extra), without a ROS install.

ROS 2's DDS middlewares (``rmw_cyclonedds_cpp``, ``rmw_fastrtps_cpp``) map a ROS topic
``/a/b`` of type ``pkg/msg/Name`` onto the DDS topic ``rt/a/b`` of type
``pkg::msg::dds_::Name_``, with the message in plain little-endian CDR (XCDR1) and every
struct ``final``. This module speaks exactly that: the bytes come from robotd's one
message model (:mod:`robotd.base.ros2msg`) and go to the wire as they are
(:meth:`RawWriter.write`); samples are taken as bytes and decoded by the same model
(:meth:`RawReader.take`). The ``cyclonedds`` ``IdlStruct`` types built here from the same
definitions only give the DDS topic its type name and type information for discovery.

Which network interface: Cyclone DDS reads its configuration from ``CYCLONEDDS_URI`` (the
same variable a ROS 2 install uses). Without it, Cyclone picks an interface itself and
uses multicast discovery. A test or a single-machine setup pins it to the loopback
interface with :func:`loopback_config` (no multicast, peers found by unicast on
127.0.0.1), passed to :class:`Participant` or exported as ``CYCLONEDDS_URI``.

Without ``cyclonedds`` robotd runs as before; asking for ROS 2 then raises
:class:`~robotd.base.errors.ConfigError` saying how to install it (x86_64: a wheel;
aarch64: built against a Cyclone DDS C library, see ``docs/ros2.md``).
"""

from __future__ import annotations

import functools
import logging
import os
import threading
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from robotd.base import ros2msg
from robotd.base.errors import ConfigError, DriverError

log = logging.getLogger(__name__)

INSTALL_HINT = ("install the ROS 2 extra: pip install 'robotd[ros2]' (x86_64 has wheels; on a "
                "Raspberry Pi or other aarch64 board build cyclonedds against Cyclone DDS C, "
                "see docs/ros2.md)")


def require_cyclonedds() -> Any:
    """The ``cyclonedds`` module, or :class:`ConfigError` saying how to install it."""
    try:
        import cyclonedds  # noqa: F401
        import cyclonedds.domain  # noqa: F401
    except ImportError as exc:
        raise ConfigError(f"ROS 2 output or input needs the cyclonedds package, which is not "
                          f"importable ({exc}); {INSTALL_HINT}") from None
    return cyclonedds


def available() -> bool:
    """Whether ``cyclonedds`` can be imported."""
    try:
        require_cyclonedds()
    except ConfigError:
        return False
    return True


def loopback_config(*, interface: str = "lo") -> str:
    """A Cyclone DDS configuration (XML text) that keeps all traffic on ``interface``
    (default the loopback): no multicast, peers discovered by unicast on 127.0.0.1 (SPDP
    to the usual participant ports). For tests and single-machine setups."""
    return ("<CycloneDDS><Domain Id=\"any\"><General>"
            f"<Interfaces><NetworkInterface name=\"{interface}\"/></Interfaces>"
            "<AllowMulticast>false</AllowMulticast></General>"
            "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>50"
            "</MaxAutoParticipantIndex><Peers><Peer Address=\"127.0.0.1\"/></Peers></Discovery>"
            "</Domain></CycloneDDS>")


@dataclass(frozen=True)
class QosSpec:
    """The QoS of a ROS 2 topic, in ROS 2's terms.

    ``reliable``: RELIABLE (else BEST_EFFORT); ``transient_local``: late joiners get the
    last ``depth`` samples (``/tf_static``); ``depth``: KEEP_LAST depth.
    """

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10


QOS_DEFAULT = QosSpec()
"""ROS 2's default publisher QoS: reliable, volatile, keep last 10."""
QOS_TF = QosSpec(depth=100)
"""tf2's ``TransformBroadcaster``: reliable, volatile, keep last 100."""
QOS_TF_STATIC = QosSpec(transient_local=True, depth=1)
"""tf2's ``StaticTransformBroadcaster``: reliable, transient local, keep last 1."""
QOS_SENSOR = QosSpec(reliable=False, depth=5)
"""ROS 2's ``SensorDataQoS``: best effort, volatile, keep last 5."""


def domain_id_from(configured: int) -> int:
    """The domain to join: ``configured`` when >= 0, else ``ROS_DOMAIN_ID`` (0 when unset),
    as a ROS 2 node does. A bad ``ROS_DOMAIN_ID`` is a :class:`ConfigError`."""
    if configured >= 0:
        return configured
    raw = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return 0
    try:
        value = int(raw)
    except ValueError:
        raise ConfigError(f"ROS_DOMAIN_ID={raw!r} is not a number") from None
    if not 0 <= value <= 232:
        raise ConfigError(f"ROS_DOMAIN_ID={value} is outside 0..232")
    return value


_TYPES: dict[str, Any] = {}
_TYPES_LOCK = threading.Lock()


def idl_type(full_name: str, distro: str | None = None) -> Any:
    """The ``cyclonedds`` ``IdlStruct`` class of ``full_name`` (built once from
    :data:`robotd.base.ros2msg.DEFINITIONS`, or ``distro``'s where it differs), named as
    ROS 2 names it."""
    with _TYPES_LOCK:
        return _idl_type_locked(full_name, distro if distro in ros2msg.DISTRO_DEFINITIONS else None)


def _idl_type_locked(full_name: str, distro: str | None = None) -> Any:
    key = full_name if distro is None else f"{full_name}@{distro}"
    cls = _TYPES.get(key)
    if cls is not None:
        return cls
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl import types as t

    prim = {"bool": bool, "byte": t.byte, "char": t.uint8, "int8": t.int8, "uint8": t.uint8,
            "int16": t.int16, "uint16": t.uint16, "int32": t.int32, "uint32": t.uint32,
            "int64": t.int64, "uint64": t.uint64, "float32": t.float32, "float64": t.float64,
            "string": str}
    fields: dict[str, Any] = {}
    for f in ros2msg.parse_definition(full_name, ros2msg.definitions(distro)[full_name]):
        ftype = prim[f.type] if f.type in prim else _idl_type_locked(f.type, distro)
        if f.array == "fixed":
            ftype = t.array[ftype, f.length]
        elif f.array == "sequence":
            ftype = t.sequence[ftype]
        fields[f.name] = ftype
    pkg, _, name = full_name.split("/")
    cls = make_idl_struct(f"{pkg}_{name}_" + (f"{distro}_" if distro else ""), ros2msg.dds_type_name(full_name),
                          fields)
    _TYPES[key] = cls
    return cls


DISCOVERY_TOPIC = "ros_discovery_info"
"""The DDS topic (no ``rt/`` prefix: it is not a ROS topic) of ROS 2's graph information."""
DISCOVERY_TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"
QOS_DISCOVERY = QosSpec(transient_local=True, depth=1)
"""``ros_discovery_info``'s QoS in ``rmw_dds_common``: reliable, transient local, keep last 1."""


def ros_distro() -> str:
    """The ROS 2 distribution whose ``ros_discovery_info`` layout to speak: ``ROS_DISTRO``
    (what a sourced ROS 2 environment sets) when it is one of ``humble``, ``jazzy``,
    ``kilted``; otherwise ``jazzy`` (Kilted has the same layout; only Humble's GID is
    longer), logged when ``ROS_DISTRO`` names another."""
    raw = os.environ.get("ROS_DISTRO", "").strip().lower()
    if raw in ros2msg.DISTROS:
        return raw
    if raw:
        log.warning("ROS_DISTRO=%s is not one robotd knows (%s): ros_discovery_info as jazzy has it",
                    raw, ", ".join(ros2msg.DISTROS))
    return "jazzy"


@functools.lru_cache(maxsize=None)
def discovery_codec(distro: str | None = None) -> ros2msg.Codec:
    """The codec of ``ros_discovery_info`` in ``distro``."""
    return ros2msg.Codec(DISCOVERY_TYPE, ros2msg.definitions(distro))


def _qos(spec: QosSpec) -> Any:
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    return Qos(
        Policy.Reliability.Reliable(duration(milliseconds=100)) if spec.reliable
        else Policy.Reliability.BestEffort,
        Policy.Durability.TransientLocal if spec.transient_local else Policy.Durability.Volatile,
        Policy.History.KeepLast(spec.depth),
    )


class Participant:
    """One DDS domain participant; a context manager. ``domain_id``: 0..232;
    ``config``: Cyclone DDS XML (e.g. :func:`loopback_config`) or None for the
    environment's (``CYCLONEDDS_URI``)."""

    def __init__(self, domain_id: int, *, config: str | None = None) -> None:
        require_cyclonedds()
        from cyclonedds.core import Policy, Qos
        from cyclonedds.domain import Domain, DomainParticipant

        if not 0 <= domain_id <= 232:
            raise ConfigError(f"ROS 2 domain id {domain_id} is outside 0..232")
        self.domain_id = domain_id
        try:
            # A Domain entity with an explicit configuration must exist before the participant.
            self._domain = Domain(domain_id, config) if config is not None else None
            # ROS 2's rmw puts the security enclave in the participant's user data
            self.dp = DomainParticipant(domain_id, qos=Qos(Policy.Userdata(b"enclave=/;")))
        except Exception as exc:  # noqa: BLE001 - cyclonedds raises DDSException with a code
            raise DriverError(f"DDS domain {domain_id}: cannot create a participant: {exc}") from exc
        self._topics: dict[str, Any] = {}
        self._closed = False
        self.writers: list[RawWriter] = []
        self.readers: list[RawReader] = []
        self._discovery: RawWriter | None = None

    @property
    def guid(self) -> bytes:
        """The participant's DDS GUID (16 bytes), its GID in ROS 2's graph."""
        return self.dp.guid.bytes

    def topic(self, dds_topic: str, full_name: str, distro: str | None = None) -> Any:
        """The DDS topic ``dds_topic`` (``rt/...``) of ROS type ``full_name`` (one per name)."""
        from cyclonedds.topic import Topic

        tp = self._topics.get(dds_topic)
        if tp is None:
            tp = self._topics[dds_topic] = Topic(self.dp, dds_topic, idl_type(full_name, distro))
        return tp

    def writer(self, topic: str, full_name: str, qos: QosSpec = QOS_DEFAULT, *,
               namespace: str = "") -> RawWriter:
        """A writer of ROS 2 topic ``topic`` (relative names resolve in ``namespace``)."""
        from cyclonedds.pub import DataWriter

        name = ros2msg.dds_topic_name(topic, namespace)
        w = DataWriter(self.dp, self.topic(name, full_name), qos=_qos(qos))
        self.writers.append(RawWriter(w, name, full_name))
        return self.writers[-1]

    def reader(self, topic: str, full_name: str, qos: QosSpec = QOS_DEFAULT, *,
               namespace: str = "") -> RawReader:
        """A reader of ROS 2 topic ``topic``."""
        from cyclonedds.sub import DataReader

        name = ros2msg.dds_topic_name(topic, namespace)
        r = DataReader(self.dp, self.topic(name, full_name), qos=_qos(qos))
        self.readers.append(RawReader(r, name, full_name))
        return self.readers[-1]

    def announce(self, node_name: str, namespace: str = "", distro: str | None = None) -> bytes:
        """Publish (again) this participant's ``ros_discovery_info``: one node ``node_name``
        in ``namespace`` holding every reader and writer made so far, as a ROS 2 node's
        ``rmw`` does (reliable, transient local, keep last 1; ``distro``'s message layout,
        see :func:`ros_distro`), so that ``ros2 node list`` can name it. Returns the bytes."""
        from cyclonedds.pub import DataWriter

        full_name = DISCOVERY_TYPE
        if self._discovery is None:
            tp = self.topic(DISCOVERY_TOPIC, full_name, distro)
            w = DataWriter(self.dp, tp, qos=_qos(QOS_DISCOVERY))
            self._discovery = RawWriter(w, DISCOVERY_TOPIC, full_name)
        ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
        msg = ros2msg.participant_entities_info(self.guid, ns, node_name, [r.guid for r in self.readers],
                                                [w.guid for w in self.writers], distro)
        data = discovery_codec(distro).encode(msg)
        self._discovery.write(data)
        return data

    def discovery_reader(self, distro: str | None = None) -> RawReader:
        """A reader of ``ros_discovery_info`` (what ``ros2 node list`` reads), in
        ``distro``'s layout; decode with :func:`discovery_codec`."""
        from cyclonedds.sub import DataReader

        r = DataReader(self.dp, self.topic(DISCOVERY_TOPIC, DISCOVERY_TYPE, distro), qos=_qos(QOS_DISCOVERY))
        return RawReader(r, DISCOVERY_TOPIC, DISCOVERY_TYPE)

    def close(self) -> None:
        """Delete the participant and everything under it; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._topics.clear()
        try:
            self.dp._delete()  # noqa: SLF001 - cyclonedds deletes entities on GC otherwise
        except Exception:  # noqa: BLE001
            log.debug("deleting the DDS participant failed", exc_info=True)

    def __enter__(self) -> Participant:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class RawWriter:
    """Writes CDR bytes of one ROS type to one topic. ``written``/``bytes_written`` count."""

    def __init__(self, writer: Any, dds_topic: str, full_name: str) -> None:
        from cyclonedds._clayer import ddspy_write, ddspy_write_ts

        self._w = writer
        self._write = ddspy_write
        self._write_ts = ddspy_write_ts
        self.dds_topic = dds_topic
        self.full_name = full_name
        self.written = 0
        self.bytes_written = 0
        self.guid = writer.guid.bytes
        """The writer's DDS GUID (16 bytes), its GID in ROS 2's graph."""

    def write(self, data: bytes, source_timestamp_ns: int | None = None) -> None:
        """Send ``data`` (CDR with its encapsulation header, from :mod:`robotd.base.ros2msg`),
        padded to a multiple of 4 bytes as Cyclone's own writers pad it."""
        pad = -len(data) % 4
        if pad:
            data = data + b"\x00" * pad
        ret = (self._write(self._w._ref, data) if source_timestamp_ns is None
               else self._write_ts(self._w._ref, data, int(source_timestamp_ns)))
        if ret < 0:
            raise DriverError(f"DDS write on {self.dds_topic} failed (code {ret})")
        self.written += 1
        self.bytes_written += len(data)

    def publish(self, msg: dict[str, Any]) -> None:
        """Encode ``msg`` with the model and write it."""
        self.write(ros2msg.encode(self.full_name, msg))

    def matched(self) -> int:
        """Readers currently matched (subscribers that discovered this writer)."""
        return int(self._w.get_publication_matched_status().current_count)


class RawReader:
    """Takes CDR samples of one ROS type from one topic."""

    def __init__(self, reader: Any, dds_topic: str, full_name: str) -> None:
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState

        self._r = reader
        self._take = ddspy_take
        self._mask = SampleState.Any | ViewState.Any | InstanceState.Any
        self.condition = ReadCondition(reader, self._mask)
        self.dds_topic = dds_topic
        self.full_name = full_name
        self.taken = 0
        self.invalid = 0
        """Samples without data (a writer left or disposed): skipped."""
        self.guid = reader.guid.bytes
        """The reader's DDS GUID (16 bytes)."""

    def take(self, n: int = 64) -> list[bytes]:
        """Up to ``n`` waiting samples' CDR bytes (samples without data are skipped and
        counted in :attr:`invalid`)."""
        ret = self._take(self._r._ref, self._mask, n)
        if isinstance(ret, int):
            raise DriverError(f"DDS take on {self.dds_topic} failed (code {ret})")
        out = []
        for data, info in ret:
            if info.valid_data:
                out.append(bytes(data))
            else:
                self.invalid += 1
        self.taken += len(out)
        return out

    def take_decoded(self, n: int = 64) -> list[dict[str, Any]]:
        """:meth:`take`, each decoded with the model."""
        return [ros2msg.decode(self.full_name, d) for d in self.take(n)]

    def matched(self) -> int:
        """Writers currently matched."""
        return int(self._r.get_subscription_matched_status().current_count)


class WaitSet:
    """Waits for data on several readers."""

    def __init__(self, participant: Participant, readers: list[RawReader]) -> None:
        from cyclonedds.core import WaitSet as _WaitSet

        self._ws = _WaitSet(participant.dp)
        for r in readers:
            self._ws.attach(r.condition)

    def wait(self, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` for data on any reader; True when some is waiting."""
        from cyclonedds.util import duration

        return self._ws.wait(duration(seconds=max(0.0, timeout_s))) > 0


__all__ = ["Participant", "QosSpec", "RawReader", "RawWriter", "WaitSet", "available",
           "discovery_codec", "domain_id_from", "idl_type", "loopback_config", "require_cyclonedds", "ros_distro",
           "DISCOVERY_TOPIC", "DISCOVERY_TYPE", "QOS_DISCOVERY",
           "QOS_DEFAULT", "QOS_SENSOR", "QOS_TF", "QOS_TF_STATIC"]
