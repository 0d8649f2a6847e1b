"""Writing rosbag2 bags without ROS (``rosbags``), and rosbags message builders.

``BagWriter`` writes a rosbag2 bag (sqlite3 by default, or MCAP) with the ROS 2 Jazzy typestore.
Messages are rosbags objects built from ``writer.typestore`` (or with the ``make_*`` helpers
below). ``/tf_static`` is registered with a transient-local ("latched") offered QoS profile so
``ros2 bag play`` latches it like ``static_transform_publisher`` does.

>>> with BagWriter(tmp / "sim") as w:                       # doctest: +SKIP
...     w.add_topic("/scan", "sensor_msgs/msg/LaserScan")
...     w.write("/scan", t_ns, make_laser_scan(w.typestore, t_ns, "laser", ...))

"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.typesys import TypesysError

from localization.bags.reader import BagError, describe_error, jazzy_typestore
from localization.core.geometry import yaw_to_quaternion

_INFINITE = QosTime(2147483647, 4294967295)  # rosbag2's "infinite" duration, as rosbags writes it

#: Offered QoS of a latched topic (``/tf_static``): reliable, transient local, keep last 1.
LATCHED_QOS = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                  _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False)
#: Offered QoS of an ordinary topic: reliable, volatile, keep last 10.
RELIABLE_QOS = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
                   _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False)
#: Offered QoS of a sensor-data publisher: best effort, volatile, keep last 5.
SENSOR_QOS = RELIABLE_QOS._replace(depth=5, reliability=QosReliability.BEST_EFFORT)

_QOS_NAMES = {
    "latched": LATCHED_QOS, "transient_local": LATCHED_QOS,
    "reliable": RELIABLE_QOS, "default": RELIABLE_QOS,
    "sensor_data": SENSOR_QOS, "best_effort": SENSOR_QOS,
}
LATCHED_TOPICS = frozenset({"/tf_static"})


def _qos_list(topic: str, qos) -> list:
    if qos is None:
        return [LATCHED_QOS if topic in LATCHED_TOPICS else RELIABLE_QOS]
    if isinstance(qos, str):
        try:
            return [_QOS_NAMES[qos.lower()]]
        except KeyError:
            raise BagError(f"unknown QoS name {qos!r}; use one of {sorted(_QOS_NAMES)}") from None
    if isinstance(qos, Qos):
        return [qos]
    return list(qos)


class BagWriter:
    """Write a rosbag2 bag (a new directory) with the ROS 2 Jazzy typestore.

    ``storage``: ``'sqlite3'`` (default) or ``'mcap'``. Use as a context manager (or call
    ``open()`` / ``close()``); if the ``with`` body raises, the bag is still closed with the
    messages written so far. Topics may be declared with ``add_topic`` or are declared on the
    first ``write`` from the message's type. The written bag has ``metadata.yaml`` (rosbag2
    version ``Writer.VERSION_LATEST``, 9 in rosbags 0.11) and embedded message definitions.
    """

    def __init__(self, path, *, storage: str = "sqlite3", typestore=None, overwrite: bool = False) -> None:
        self.path = Path(path)
        plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
        try:
            self._plugin = plugins[storage.lower()]
        except KeyError:
            raise BagError(f"unknown storage {storage!r}; use 'sqlite3' or 'mcap'") from None
        self.storage = storage.lower()
        self.typestore = typestore if typestore is not None else jazzy_typestore()
        self._overwrite = overwrite
        self._writer: Writer | None = None
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    # -- lifecycle --------------------------------------------------------------------------
    def open(self) -> BagWriter:
        if self._writer is not None:
            return self
        if self.path.exists():
            if not self._overwrite:
                raise BagError(f"cannot write bag {self.path}: it exists already")
            import shutil
            if self.path.is_dir():
                shutil.rmtree(self.path)
            else:
                self.path.unlink()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=self._plugin)
            writer.open()
        except (WriterError, OSError) as exc:
            raise BagError(f"cannot write bag {self.path}: {describe_error(exc)}") from None
        self._writer = writer
        return self

    def close(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except (WriterError, OSError) as exc:
                raise BagError(f"cannot finish bag {self.path}: {describe_error(exc)}") from None

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- topics and messages ----------------------------------------------------------------
    @property
    def topics(self) -> dict[str, str]:
        return {t: c.msgtype for t, c in self._conns.items()}

    def add_topic(self, topic: str, msgtype: str, qos=None) -> None:
        """Declare ``topic`` with ``msgtype`` (ROS 2 form, e.g. ``'nav_msgs/msg/Odometry'``).

        ``qos``: the offered QoS profile(s) stored in the metadata: ``None`` (transient local
        for ``/tf_static``, reliable volatile otherwise), a name (``'latched'``,
        ``'reliable'``, ``'sensor_data'``), a rosbags ``Qos`` or a list of them.
        """
        if self._writer is None:
            self.open()
        if topic in self._conns:
            if self._conns[topic].msgtype != msgtype:
                raise BagError(f"topic {topic} already added with type {self._conns[topic].msgtype}, not {msgtype}")
            return
        if msgtype not in self.typestore.types:
            raise BagError(f"unknown message type {msgtype!r} (not in the typestore)")
        try:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore,
                                               offered_qos_profiles=_qos_list(topic, qos))
        except (WriterError, TypesysError) as exc:
            raise BagError(f"cannot add topic {topic} to {self.path}: {describe_error(exc)}") from None
        self._conns[topic] = conn
        self.counts[topic] = 0

    def write(self, topic: str, t_ns: int, msg) -> None:
        """Write rosbags message object ``msg`` on ``topic`` at bag time ``t_ns`` (ns)."""
        msgtype = getattr(msg, "__msgtype__", None)
        if msgtype is None:
            raise BagError(f"write({topic!r}): expected a rosbags message object, got {type(msg).__name__}")
        if topic not in self._conns:
            self.add_topic(topic, msgtype)
        conn = self._conns[topic]
        if conn.msgtype != msgtype:
            raise BagError(f"write({topic!r}): topic has type {conn.msgtype}, message is {msgtype}")
        try:
            data = self.typestore.serialize_cdr(msg, msgtype)
        except Exception as exc:  # noqa: BLE001 - serializer raises assorted errors on bad fields
            raise BagError(f"cannot serialize {msgtype} for {topic}: {exc}") from None
        self._write(topic, conn, t_ns, data)

    def write_raw(self, topic: str, t_ns: int, cdr: bytes) -> None:
        """Write already CDR-serialized bytes on a topic declared with ``add_topic``."""
        if topic not in self._conns:
            raise BagError(f"write_raw({topic!r}): add_topic first")
        self._write(topic, self._conns[topic], t_ns, cdr)

    def _write(self, topic, conn, t_ns, data) -> None:
        if self._writer is None:
            raise BagError(f"bag {self.path} is not open")
        t_ns = int(t_ns)
        if t_ns < 0:
            raise BagError(f"negative timestamp {t_ns} for {topic}")
        self._writer.write(conn, t_ns, data)
        self.counts[topic] += 1


# --------------------------------------------------------------------------------------------
# Message helpers (rosbags objects; ``typestore`` is e.g. ``BagWriter.typestore``)
# --------------------------------------------------------------------------------------------


def stamp_to_ns(stamp) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def make_time(typestore, t_ns: int):
    t_ns = int(t_ns)
    return typestore.types["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


def make_header(typestore, t_ns: int, frame_id: str):
    """``std_msgs/msg/Header`` with stamp ``t_ns`` (ns) and ``frame_id``."""
    return typestore.types["std_msgs/msg/Header"](stamp=make_time(typestore, t_ns), frame_id=frame_id)


def _quat(typestore, yaw: float):
    x, y, z, w = (float(v) for v in yaw_to_quaternion(yaw))
    return typestore.types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)


def make_pose(typestore, x: float, y: float, yaw: float):
    """``geometry_msgs/msg/Pose``: planar pose (x, y, yaw)."""
    T = typestore.types
    return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                       orientation=_quat(typestore, float(yaw)))


def _cov36(cov) -> np.ndarray:
    out = np.zeros(36, dtype=np.float64)
    if cov is not None:
        arr = np.asarray(cov, dtype=np.float64).ravel()
        if arr.size != 36:
            raise BagError(f"covariance needs 36 values, got {arr.size}")
        out[:] = arr
    return out


def make_laser_scan(typestore, t_ns: int, frame_id: str, ranges, *, angle_min: float, angle_max: float,
                    angle_increment: float, range_min: float, range_max: float, intensities=None,
                    time_increment: float = 0.0, scan_time: float = 0.0):
    """``sensor_msgs/msg/LaserScan``; ``ranges`` / ``intensities`` become float32 arrays."""
    r = np.ascontiguousarray(ranges, dtype=np.float32).ravel()
    if intensities is None:
        i = np.zeros(0, dtype=np.float32)
    else:
        i = np.ascontiguousarray(intensities, dtype=np.float32).ravel()
    return typestore.types["sensor_msgs/msg/LaserScan"](
        header=make_header(typestore, t_ns, frame_id), angle_min=float(angle_min), angle_max=float(angle_max),
        angle_increment=float(angle_increment), time_increment=float(time_increment), scan_time=float(scan_time),
        range_min=float(range_min), range_max=float(range_max), ranges=r, intensities=i)


def make_odometry(typestore, t_ns: int, frame_id: str, child_frame_id: str, x: float, y: float, yaw: float,
                  vx: float = 0.0, vy: float = 0.0, wz: float = 0.0, *, pose_covariance=None,
                  twist_covariance=None):
    """``nav_msgs/msg/Odometry``: planar pose (x, y, yaw) in ``frame_id``, twist in ``child_frame_id``."""
    T = typestore.types
    pose = make_pose(typestore, x, y, yaw)
    twist = T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=float(vx), y=float(vy), z=0.0),
                                         angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=float(wz)))
    return T["nav_msgs/msg/Odometry"](
        header=make_header(typestore, t_ns, frame_id), child_frame_id=child_frame_id,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_cov36(pose_covariance)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=_cov36(twist_covariance)))


def make_transform_stamped(typestore, t_ns: int, parent_frame: str, child_frame: str, x: float = 0.0,
                           y: float = 0.0, z: float = 0.0, yaw: float = 0.0, *,
                           quaternion: Sequence[float] | None = None):
    """``geometry_msgs/msg/TransformStamped`` parent -> child; rotation by ``yaw`` or ``quaternion`` (x, y, z, w)."""
    T = typestore.types
    if quaternion is None:
        rot = _quat(typestore, float(yaw))
    else:
        qx, qy, qz, qw = (float(v) for v in quaternion)
        rot = T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
    translation = T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))
    tf = T["geometry_msgs/msg/Transform"](translation=translation, rotation=rot)
    return T["geometry_msgs/msg/TransformStamped"](header=make_header(typestore, t_ns, parent_frame),
                                                   child_frame_id=child_frame, transform=tf)


def make_tf_message(typestore, transforms: Iterable):
    """``tf2_msgs/msg/TFMessage`` holding ``transforms`` (``TransformStamped`` objects)."""
    return typestore.types["tf2_msgs/msg/TFMessage"](transforms=list(transforms))
