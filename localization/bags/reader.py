"""Bag input/output without ROS: read ROS 1 and ROS 2 bags, write rosbag2 bags.

Everything here uses the pure-Python ``rosbags`` package (plus numpy and the standard library);
nothing imports rclpy, so it works in plain scripts, in tests and inside ROS nodes alike.

Reading
-------
``open_bag(path)`` opens a ROS 2 bag (a rosbag2 directory with ``metadata.yaml``, or a bare
``.db3`` / ``.mcap`` storage file) or a ROS 1 ``.bag`` file with ``rosbags.highlevel.AnyReader``.
Message types come from the definitions embedded in the bag; bags without embedded definitions
fall back to the ROS 2 Jazzy typestore. Message type names are always in ROS 2 form
(``'sensor_msgs/msg/LaserScan'``), also for ROS 1 bags.

>>> with open_bag("run.bag") as bag:                        # doctest: +SKIP
...     for m in bag.messages(["/scan"]):
...         print(m.t_ns, m.msg.header.stamp.sec, m.msg.ranges.shape)

or without a context manager: ``topics(path)``, ``read_messages(path, topics)``, ``bag_info(path)``.

Each ``BagMessage`` has ``topic``, ``msgtype``, ``t_ns`` (the bag's receive time in ns) and two
lazily computed views of the payload:

* ``msg``: the deserialized rosbags message object; its fields mirror the ROS message
  (``msg.header.stamp.sec`` / ``.nanosec``, ``msg.ranges`` as a numpy ``float32`` array ...).
  Messages from ROS 1 bags keep their ROS 1 layout, e.g. ``msg.header.seq`` exists.
* ``raw_cdr``: ``bytes``, the CDR serialization a ROS 2 publisher sends. For ROS 2 bags this is
  the stored data; ROS 1 messages are converted with ``Typestore.ros1_to_cdr`` (which also drops
  the ROS 1-only ``Header.seq``).

Neither is computed unless asked for, so a replay that needs only ``msg`` never pays for the
CDR conversion and a player that needs only ``raw_cdr`` never deserializes.

Errors: a missing or unreadable bag raises ``BagError`` (a ``ValueError``) with one clear message.
"""
from __future__ import annotations

import re
import sqlite3
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import QosDurability
from rosbags.rosbag1 import ReaderError as Rosbag1ReaderError
from rosbags.rosbag2 import ReaderError as Rosbag2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore

#: Typestore used for writing and as fallback for bags without embedded message definitions.
DEFAULT_TYPESTORE = Stores.ROS2_JAZZY

#: Files ``open_bag`` accepts directly (besides rosbag2 directories).
ROS2_BAG_SUFFIXES = (".db3", ".mcap")
ROS1_BAG_SUFFIX = ".bag"

_JAZZY = None


def jazzy_typestore():
    """The (shared, cached) ROS 2 Jazzy rosbags typestore."""
    global _JAZZY
    if _JAZZY is None:
        _JAZZY = get_typestore(DEFAULT_TYPESTORE)
    return _JAZZY


class _JazzyOnDemand:
    """``AnyReader``'s default typestore, built only when a bag carries no definitions of its own (ROS 1
    bags and most rosbag2 bags do): the Jazzy store takes about 50 ms to build."""

    def __bool__(self) -> bool:
        return True

    @property
    def fielddefs(self) -> dict:
        return jazzy_typestore().fielddefs


class BagError(ValueError):
    """A bag is missing, unreadable, or used wrongly (one clear message)."""


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


class _Codec:
    """Turns stored payloads into message objects and ROS 2 CDR, for one open bag.

    For ROS 1 bags the bag's own (ROS 1) definitions deserialize ``msg``. ``ros1_to_cdr`` needs
    a typestore whose ``std_msgs/msg/Header`` is the ROS 2 one (the converter itself skips the
    ROS 1 ``seq``), so a second typestore with the bag's definitions but the ROS 2 Header is
    built the first time CDR is asked for (as ``rosbags-convert`` does).
    """

    def __init__(self, typestore, is_ros1: bool) -> None:
        self.typestore = typestore
        self.is_ros1 = is_ros1
        self._cdr_typestore = None

    def deserialize(self, raw, msgtype: str):
        if self.is_ros1:
            return self.typestore.deserialize_ros1(raw, msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    def to_cdr(self, raw, msgtype: str) -> bytes:
        if not self.is_ros1:
            return bytes(raw)
        if self._cdr_typestore is None:
            store = get_typestore(Stores.EMPTY)
            store.register({**self.typestore.fielddefs,
                            "std_msgs/msg/Header": jazzy_typestore().fielddefs["std_msgs/msg/Header"]})
            self._cdr_typestore = store
        return bytes(self._cdr_typestore.ros1_to_cdr(raw, msgtype))


class BagMessage:
    """One message of a bag: ``topic``, ``msgtype``, ``t_ns`` plus lazy ``msg`` and ``raw_cdr``.

    ``t_ns`` is the bag (receive/record) time in nanoseconds, not the header stamp. Unpacks like
    a tuple: ``topic, msgtype, t_ns, msg, raw_cdr = m`` (which computes both payload views).
    """

    __slots__ = ("topic", "msgtype", "t_ns", "_raw", "_codec", "_msg", "_cdr")

    def __init__(self, topic: str, msgtype: str, t_ns: int, raw: bytes, codec: _Codec) -> None:
        self.topic = topic
        self.msgtype = msgtype
        self.t_ns = int(t_ns)
        self._raw = raw
        self._codec = codec
        self._msg = None
        self._cdr = None

    @property
    def msg(self) -> Any:
        """The deserialized rosbags message object (computed on first access, then cached)."""
        if self._msg is None:
            try:
                self._msg = self._codec.deserialize(self._raw, self.msgtype)
            except (SerdeError, TypesysError, KeyError) as exc:
                raise BagError(f"cannot deserialize {self.msgtype} message on {self.topic} "
                               f"at t={self.t_ns}: {exc}") from None
        return self._msg

    @property
    def raw_cdr(self) -> bytes:
        """The message as ROS 2 CDR bytes (for ``rclpy`` ``publisher.publish(bytes)``); cached."""
        if self._cdr is None:
            try:
                self._cdr = self._codec.to_cdr(self._raw, self.msgtype)
            except (SerdeError, TypesysError, KeyError) as exc:
                raise BagError(f"cannot convert {self.msgtype} message on {self.topic} to CDR: {exc}") from None
        return self._cdr

    @property
    def raw(self) -> bytes:
        """The payload exactly as stored in the bag (ROS 1 serialization for ROS 1 bags)."""
        return bytes(self._raw)

    @property
    def is_ros1(self) -> bool:
        return self._codec.is_ros1

    _fields = ("topic", "msgtype", "t_ns", "msg", "raw_cdr")

    def __iter__(self) -> Iterator[Any]:
        return iter((self.topic, self.msgtype, self.t_ns, self.msg, self.raw_cdr))

    def __repr__(self) -> str:
        return f"BagMessage(topic={self.topic!r}, msgtype={self.msgtype!r}, t_ns={self.t_ns}, {len(self._raw)} bytes)"


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a bag: ROS 2 message type name, message count, offered QoS (rosbag2 only)."""

    name: str
    msgtype: str
    count: int
    offered_qos: tuple = ()  # rosbags Qos entries from a rosbag2's metadata; empty for ROS 1
    latched: bool = False  # ROS 1 latching or a transient-local offered profile


@dataclass(frozen=True)
class BagInfo:
    """Summary of a bag (times are bag receive times in ns)."""

    path: Path
    ros_version: int  # 1 or 2
    start_ns: int
    end_ns: int  # time of the last message
    message_count: int
    topics: dict[str, TopicInfo] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) * 1e-9


def _resolve_path(path) -> Path:
    """Check ``path`` and return what ``AnyReader`` should open; raise ``BagError`` otherwise."""
    try:
        p = Path(path).expanduser()
    except TypeError:
        raise BagError(f"not a bag path: {path!r}") from None
    if not p.exists():
        raise BagError(f"bag not found: {p}")
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return p
        # A directory holding exactly one storage file but no metadata.yaml: open that file.
        files = sorted(x for x in p.iterdir() if x.suffix in ROS2_BAG_SUFFIXES + (ROS1_BAG_SUFFIX,))
        if len(files) == 1:
            return files[0]
        raise BagError(f"not a rosbag2 directory (no metadata.yaml): {p}")
    if p.suffix not in ROS2_BAG_SUFFIXES + (ROS1_BAG_SUFFIX,):
        raise BagError(f"unsupported bag file {p} (expected a rosbag2 directory, .db3, .mcap or a ROS 1 .bag)")
    return p


try:  # rosbags reads rosbag2's SQLite storage through apsw
    from apsw import Error as _ApswError
except ImportError:  # pragma: no cover - rosbags without apsw
    _ApswError = sqlite3.Error

_OPEN_ERRORS = (AnyReaderError, Rosbag1ReaderError, Rosbag2ReaderError, TypesysError, SerdeError, OSError,
                KeyError, EOFError, struct.error, sqlite3.Error, _ApswError)


def _type_deps(fielddefs: dict, name: str, out: set) -> None:
    """Collect ``name`` and every message type it references (recursively) into ``out``."""
    if name in out or name not in fielddefs:
        return
    out.add(name)

    def walk(node):
        if isinstance(node, str):
            if node in fielddefs:
                _type_deps(fielddefs, node, out)
        elif isinstance(node, (tuple, list)):
            for item in node:
                walk(item)

    walk(fielddefs[name][1])


class BagReader:
    """An open bag. Use ``open_bag(path)``; close it (or use ``with``) when done."""

    def __init__(self, path) -> None:
        self.path = _resolve_path(path)
        self.ros_version = 1 if self.path.suffix == ROS1_BAG_SUFFIX else 2
        try:
            self._reader = AnyReader([self.path], default_typestore=_JazzyOnDemand())
            self._reader.open()
        except _OPEN_ERRORS as exc:
            raise BagError(f"cannot read bag {self.path}: {describe_error(exc)}") from None
        self.typestore = self._reader.typestore
        self._end_ns: int | None = None
        self._complete_typestore()
        self._codec = _Codec(self.typestore, self.ros_version == 1)

    def _complete_typestore(self) -> None:
        """Add Jazzy definitions for types the bag uses but does not define (mixed bags)."""
        have = self.typestore.fielddefs
        missing = {c.msgtype for c in self._reader.connections if c.msgtype not in have}
        if not missing:
            return
        jazzy = jazzy_typestore().fielddefs
        unknown = sorted(t for t in missing if t not in jazzy)
        if unknown:
            self.close()
            raise BagError(f"cannot read bag {self.path}: no message definition for {', '.join(unknown)}")
        need: set = set()
        for t in missing:
            _type_deps(jazzy, t, need)
        try:
            self.typestore.register({t: jazzy[t] for t in need if t not in have})
        except TypesysError as exc:
            self.close()
            raise BagError(f"cannot read bag {self.path}: {exc}") from None

    # -- context manager -------------------------------------------------------------------
    def close(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - closing must not mask the real error
                pass

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _open_reader(self) -> AnyReader:
        if self._reader is None:
            raise BagError(f"bag {self.path} is closed")
        return self._reader

    # -- metadata ---------------------------------------------------------------------------
    @property
    def topic_infos(self) -> dict[str, TopicInfo]:
        """Topics with type, message count and offered QoS, sorted by name."""
        out = {}
        for name, info in self._open_reader().topics.items():
            msgtype = info.msgtype or next((c.msgtype for c in info.connections), "")
            qos: list = []
            latched = False
            for c in info.connections:
                ext = c.ext
                if hasattr(ext, "offered_qos_profiles"):
                    qos.extend(ext.offered_qos_profiles)
                    latched = latched or any(q.durability == QosDurability.TRANSIENT_LOCAL
                                             for q in ext.offered_qos_profiles)
                elif getattr(ext, "latching", None):
                    latched = True
            out[name] = TopicInfo(name, msgtype, int(info.msgcount), tuple(qos), latched)
        return out

    @property
    def topics(self) -> dict[str, str]:
        """``{topic: msgtype}`` with ROS 2 style type names, sorted by topic."""
        return {k: v.msgtype for k, v in self.topic_infos.items()}

    @property
    def start_ns(self) -> int:
        return int(self._open_reader().start_time) if self.message_count else 0

    @property
    def end_ns(self) -> int:
        """Bag time of the last message.

        rosbags' ``end_time`` is "one past the last message" for ROS 1 bags and rosbag2
        directories but differs between storage plugins for bare ``.db3`` / ``.mcap`` files;
        those are scanned once (raw records, no deserialization) to get it exactly.
        """
        reader = self._open_reader()
        if not self.message_count:
            return 0
        if self._end_ns is None:
            if self.ros_version == 1 or self.path.is_dir():
                self._end_ns = int(reader.end_time) - 1
            else:
                try:
                    self._end_ns = max(int(t) for _, t, _ in reader.messages())
                except _OPEN_ERRORS as exc:
                    raise BagError(f"error while reading bag {self.path}: {describe_error(exc)}") from None
        return self._end_ns

    @property
    def message_count(self) -> int:
        return int(self._open_reader().message_count)

    def info(self) -> BagInfo:
        return BagInfo(self.path, self.ros_version, self.start_ns, self.end_ns, self.message_count, self.topic_infos)

    # -- messages ---------------------------------------------------------------------------
    def messages(self, topics: Iterable[str] | str | None = None, *, start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[BagMessage]:
        """Yield ``BagMessage`` s in bag-time order.

        ``topics``: names to keep (``None``: all). Names not in the bag are ignored; check
        ``self.topics`` first if that matters. ``start_ns`` / ``stop_ns``: keep messages with
        ``start_ns <= t_ns < stop_ns``.
        """
        reader = self._open_reader()
        if isinstance(topics, str):
            topics = [topics]
        if topics is None:
            conns = list(reader.connections)
        else:
            wanted = set(topics)
            conns = [c for c in reader.connections if c.topic in wanted]
            if not conns:
                return
        codec = self._codec
        try:
            for conn, t_ns, raw in reader.messages(conns, start=start_ns, stop=stop_ns):
                yield BagMessage(conn.topic, conn.msgtype, t_ns, raw, codec)
        except _OPEN_ERRORS as exc:
            raise BagError(f"error while reading bag {self.path}: {describe_error(exc)}") from None

    __iter__ = messages


#: what rosbags, apsw and the storage plugins say about a file cut short or overwritten -> what is wrong, for a user
_DAMAGED = (
    (re.compile(r"not indexed", re.I),
     "the bag has no index (its recording was never closed): run rosbag reindex on it"),
    (re.compile(r"index looks damaged|could not be read|unexpected end|truncated|\bEOF", re.I),
     "the file is truncated or damaged"),
    (re.compile(r"magic", re.I), "the file is truncated or damaged (no MCAP start or end marker)"),
    (re.compile(r"malformed|not a database|disk image", re.I),
     "the file is truncated or damaged (its SQLite database is malformed)"),
)


def _flat_text(value) -> str:
    """An exception's arguments as plain words: nested tuples and quotes unwrapped (rosbags wraps the
    original error's ``args`` tuple into its own message)."""
    if isinstance(value, BaseException):
        return _flat_text(value.args) if value.args else type(value).__name__
    if isinstance(value, (tuple, list)):
        return ", ".join(t for t in (_flat_text(v).rstrip(".") for v in value) if t)
    text = str(value)
    # "... damaged: ('Header could not be read from file.',)" -> "... damaged: Header could not be read from file."
    text = re.sub(r"\(\s*(['\"])(.*?)\1\s*,?\s*\)", r"\2", text)
    return text.strip()


def describe_error(exc: BaseException) -> str:
    """One line saying what is wrong with a bag: a known kind of damage in words a user can act on, then
    the reader library's own words; else those words alone (never a Python repr)."""
    detail = _flat_text(exc).rstrip(".")
    for pattern, meaning in _DAMAGED:
        if pattern.search(detail):
            return f"{meaning}; the reader says: {detail}"
    return detail


def open_bag(path) -> BagReader:
    """Open a ROS 1 ``.bag``, a rosbag2 directory, or a ``.db3`` / ``.mcap`` file for reading."""
    return BagReader(path)


def topics(path) -> dict[str, str]:
    """``{topic: msgtype}`` of the bag at ``path`` (type names in ROS 2 form)."""
    with open_bag(path) as bag:
        return bag.topics


def bag_info(path) -> BagInfo:
    """Summary (start/end time, counts, types, QoS) of the bag at ``path``."""
    with open_bag(path) as bag:
        return bag.info()


def read_messages(path, topics: Iterable[str] | str | None = None, *, start_ns: int | None = None,
                  stop_ns: int | None = None) -> Iterator[BagMessage]:
    """Yield the messages of the bag at ``path`` in bag-time order (see ``BagReader.messages``).

    The bag is opened immediately (so a missing bag raises ``BagError`` at the call) and closed
    when the iterator is exhausted or garbage collected.
    """
    bag = open_bag(path)
    return _closing_iter(bag, bag.messages(topics, start_ns=start_ns, stop_ns=stop_ns))


def _closing_iter(bag: BagReader, it: Iterator[BagMessage]) -> Iterator[BagMessage]:
    try:
        yield from it
    finally:
        bag.close()
