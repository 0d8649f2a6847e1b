"""Tests for localization.bag_io: rosbag2 writing/reading round trips and the real ROS 1 bags."""
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Writer

from localization.bags import (
    BagError,
    BagWriter,
    bag_info,
    jazzy_typestore,
    make_header,
    make_laser_scan,
    make_odometry,
    make_tf_message,
    make_transform_stamped,
    open_bag,
    read_messages,
    stamp_to_ns,
    topics,
)
from localization.core.geometry import compose, yaw_of

T0 = 1_700_000_000_000_000_000  # bag start, ns
N_SCANS = 8
N_ODOM = 10
N_BEAMS = 181


def _scan_ranges(k: int) -> np.ndarray:
    return (np.linspace(0.5, 10.0, N_BEAMS) + 0.01 * k).astype(np.float32)


def write_sample_bag(path: Path, storage: str = "sqlite3") -> dict:
    """A small bag: /tf_static at T0, /scan at 40 Hz, /odom at 50 Hz. Returns what was written."""
    written = {"/scan": [], "/odom": [], "/tf_static": []}
    with BagWriter(path, storage=storage) as w:
        ts = w.typestore
        w.add_topic("/tf_static", "tf2_msgs/msg/TFMessage")
        w.add_topic("/scan", "sensor_msgs/msg/LaserScan")
        w.add_topic("/odom", "nav_msgs/msg/Odometry")
        tf = make_tf_message(ts, [make_transform_stamped(ts, T0, "base_link", "laser", x=0.275, z=0.1)])
        w.write("/tf_static", T0, tf)
        written["/tf_static"].append(T0)
        for k in range(N_SCANS):
            t = T0 + 5_000_000 + k * 25_000_000
            scan = make_laser_scan(ts, t - 1_000_000, "laser", _scan_ranges(k), angle_min=-np.pi / 2,
                                   angle_max=np.pi / 2, angle_increment=np.pi / (N_BEAMS - 1), range_min=0.02,
                                   range_max=30.0, intensities=np.full(N_BEAMS, 100.0), scan_time=0.025)
            w.write("/scan", t, scan)
            written["/scan"].append(t)
        for k in range(N_ODOM):
            t = T0 + 1_000_000 + k * 20_000_000
            odom = make_odometry(ts, t, "odom", "base_link", x=0.1 * k, y=-0.05 * k, yaw=0.02 * k, vx=1.5, wz=0.2)
            w.write("/odom", t, odom)
            written["/odom"].append(t)
        assert w.counts == {"/tf_static": 1, "/scan": N_SCANS, "/odom": N_ODOM}
    return written


@pytest.fixture(params=["sqlite3", "mcap"])
def sample_bag(request, tmp_path):
    path = tmp_path / f"sample_{request.param}"
    written = write_sample_bag(path, request.param)
    return path, written, request.param


def test_written_bag_is_valid_rosbag2(sample_bag):
    path, _, storage = sample_bag
    meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == Writer.VERSION_LATEST
    assert meta["storage_identifier"] == storage
    files = meta["relative_file_paths"]
    assert len(files) == 1 and (path / files[0]).is_file()
    assert files[0].endswith(".db3" if storage == "sqlite3" else ".mcap")
    assert meta["message_count"] == 1 + N_SCANS + N_ODOM
    by_topic = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert by_topic["/scan"]["message_count"] == N_SCANS
    assert by_topic["/scan"]["topic_metadata"]["type"] == "sensor_msgs/msg/LaserScan"
    # /tf_static is offered transient local (latched), the others volatile.
    (static_qos,) = by_topic["/tf_static"]["topic_metadata"]["offered_qos_profiles"]
    assert static_qos["durability"] == "transient_local"
    assert static_qos["reliability"] == "reliable"
    (scan_qos,) = by_topic["/scan"]["topic_metadata"]["offered_qos_profiles"]
    assert scan_qos["durability"] == "volatile"


def test_round_trip(sample_bag):
    path, written, _ = sample_bag
    assert topics(path) == {
        "/odom": "nav_msgs/msg/Odometry",
        "/scan": "sensor_msgs/msg/LaserScan",
        "/tf_static": "tf2_msgs/msg/TFMessage",
    }
    msgs = list(read_messages(path))
    assert len(msgs) == 1 + N_SCANS + N_ODOM
    times = [m.t_ns for m in msgs]
    assert times == sorted(times)
    assert times == sorted(t for ts in written.values() for t in ts)
    for topic, stamps in written.items():
        assert [m.t_ns for m in msgs if m.topic == topic] == stamps

    scans = [m for m in msgs if m.topic == "/scan"]
    for k, m in enumerate(scans):
        assert m.msgtype == "sensor_msgs/msg/LaserScan"
        assert m.msg.header.frame_id == "laser"
        assert stamp_to_ns(m.msg.header.stamp) == m.t_ns - 1_000_000
        assert isinstance(m.msg.ranges, np.ndarray) and m.msg.ranges.dtype == np.float32
        np.testing.assert_array_equal(m.msg.ranges, _scan_ranges(k))
        assert m.msg.angle_min == pytest.approx(-np.pi / 2) and m.msg.range_max == 30.0
        assert len(m.msg.intensities) == N_BEAMS

    odoms = [m for m in msgs if m.topic == "/odom"]
    last = odoms[-1].msg
    assert (last.header.frame_id, last.child_frame_id) == ("odom", "base_link")
    assert last.pose.pose.position.x == pytest.approx(0.1 * (N_ODOM - 1))
    assert last.pose.pose.position.y == pytest.approx(-0.05 * (N_ODOM - 1))
    assert yaw_of(last.pose.pose.orientation) == pytest.approx(0.02 * (N_ODOM - 1))
    assert last.twist.twist.linear.x == 1.5 and last.twist.twist.angular.z == pytest.approx(0.2)
    assert last.header.stamp.sec == odoms[-1].t_ns // 10**9
    assert last.header.stamp.nanosec == odoms[-1].t_ns % 10**9

    (static,) = [m for m in msgs if m.topic == "/tf_static"]
    (tf,) = static.msg.transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", "laser")
    assert tf.transform.translation.x == pytest.approx(0.275) and tf.transform.rotation.w == pytest.approx(1.0)

    # ROS 2 bag: raw_cdr is the stored CDR and equals a fresh serialization.
    ts = jazzy_typestore()
    assert scans[0].raw_cdr == bytes(ts.serialize_cdr(scans[0].msg, "sensor_msgs/msg/LaserScan"))


def test_reader_api_info_filters_and_bare_storage_file(sample_bag):
    path, written, storage = sample_bag
    info = bag_info(path)
    assert info.ros_version == 2
    assert info.start_ns == T0
    assert info.end_ns == max(t for ts in written.values() for t in ts)
    assert info.message_count == 1 + N_SCANS + N_ODOM
    assert info.topics["/tf_static"].latched and not info.topics["/scan"].latched
    assert info.topics["/odom"].count == N_ODOM

    with open_bag(path) as bag:
        only_scan = list(bag.messages(["/scan"]))
        assert {m.topic for m in only_scan} == {"/scan"} and len(only_scan) == N_SCANS
        assert list(bag.messages(["/does_not_exist"])) == []
        window = list(bag.messages("/odom", start_ns=T0 + 41_000_000, stop_ns=T0 + 101_000_000))
        assert [m.t_ns for m in window] == written["/odom"][2:5]  # start inclusive, stop exclusive

    # The bare .db3 / .mcap file opens too (no metadata.yaml needed).
    (storage_file,) = [p for p in path.iterdir() if p.suffix in (".db3", ".mcap")]
    assert topics(storage_file) == topics(path)
    bare = list(read_messages(storage_file, ["/scan"]))
    assert [m.t_ns for m in bare] == written["/scan"]
    assert bag_info(storage_file).end_ns == info.end_ns


def test_messages_are_lazy_and_unpack(sample_bag):
    path, _, _ = sample_bag
    m = next(read_messages(path, ["/scan"]))
    assert m._msg is None and m._cdr is None  # nothing computed yet
    _ = m.msg
    assert m._cdr is None
    topic, msgtype, t_ns, msg, raw = m
    assert (topic, msgtype, t_ns) == ("/scan", "sensor_msgs/msg/LaserScan", m.t_ns)
    assert msg is m.msg and isinstance(raw, bytes)


def test_writer_rejects_bad_use(tmp_path):
    path = tmp_path / "bag"
    with BagWriter(path) as w:
        w.add_topic("/scan", "sensor_msgs/msg/LaserScan")
        odom = make_odometry(w.typestore, 1, "odom", "base_link", 0, 0, 0)
        with pytest.raises(BagError, match="/scan"):
            w.write("/scan", 1, odom)
        with pytest.raises(BagError, match="unknown message type"):
            w.add_topic("/x", "no_pkg/msg/Nothing")
        with pytest.raises(BagError):
            w.write("/scan", 1, "not a message")
        # Topics can also be declared implicitly by the first write.
        w.write("/odom", 5, odom)
        header = make_header(w.typestore, 1_500_000_000, "map")
        assert (header.stamp.sec, header.stamp.nanosec, header.frame_id) == (1, 500_000_000, "map")
    assert topics(path) == {"/odom": "nav_msgs/msg/Odometry", "/scan": "sensor_msgs/msg/LaserScan"}
    with pytest.raises(BagError, match="exists"):
        BagWriter(path).open()
    with pytest.raises(BagError, match="storage"):
        BagWriter(tmp_path / "other", storage="zip")


def test_missing_or_bad_bag_raises_bag_error(tmp_path):
    with pytest.raises(BagError, match="not found"):
        read_messages(tmp_path / "nope.bag")
    with pytest.raises(BagError):
        topics(tmp_path / "nope")
    assert issubclass(BagError, ValueError)
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(b"this is not a bag")
    with pytest.raises(BagError, match="cannot read bag"):
        open_bag(garbage)
    (tmp_path / "dir").mkdir()
    with pytest.raises(BagError, match="metadata.yaml"):
        open_bag(tmp_path / "dir")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(BagError, match="unsupported"):
        open_bag(tmp_path / "notes.txt")


def test_bag_without_definitions_reads_with_jazzy_types_built_on_demand(tmp_path, monkeypatch):
    """A bag that carries its own definitions is opened without building the Jazzy type store; one that
    carries none (an old rosbag2 sqlite3 bag) is read with Jazzy's."""
    import localization.bags.reader as reader
    path = tmp_path / "with_defs"
    written = write_sample_bag(path)  # the writer uses the Jazzy store: forget it
    monkeypatch.setattr(reader, "_JAZZY", None)
    with open_bag(path) as bag:
        assert len(list(bag.messages(["/scan"]))) == N_SCANS
    assert reader._JAZZY is None  # its own definitions sufficed

    import sqlite3
    bare = tmp_path / "no_defs"
    write_sample_bag(bare)
    for db in bare.glob("*.db3"):  # as a bag recorded before rosbag2 stored definitions
        with sqlite3.connect(db) as con:
            con.execute("DELETE FROM message_definitions")
    monkeypatch.setattr(reader, "_JAZZY", None)
    msgs = list(read_messages(bare, ["/odom"]))
    assert [m.msg.pose.pose.position.x for m in msgs] == pytest.approx([0.1 * k for k in range(N_ODOM)])
    assert [m.t_ns for m in msgs] == written["/odom"]
    assert reader._JAZZY is not None  # built for it


# ---------------------------------------------------------------------------------------------
# The real ROS 1 recordings
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bag3(shared_dir):
    path = shared_dir / "bags" / "rss2022" / "localization_bag3.bag"
    assert path.is_file(), f"missing {path}"
    return path


def test_real_ros1_bag_topics_and_rates(bag3):
    assert topics(bag3) == {"/scan": "sensor_msgs/msg/LaserScan", "/vesc/odom": "nav_msgs/msg/Odometry"}
    info = bag_info(bag3)
    assert info.ros_version == 1
    assert 5.0 < info.duration_s < 6.0
    msgs = list(read_messages(bag3))
    assert len(msgs) == info.message_count
    assert msgs[0].t_ns == info.start_ns and msgs[-1].t_ns == info.end_ns
    assert all(a.t_ns <= b.t_ns for a, b in zip(msgs, msgs[1:]))

    scans = [m for m in msgs if m.topic == "/scan"]
    odoms = [m for m in msgs if m.topic == "/vesc/odom"]
    assert len(scans) == info.topics["/scan"].count
    assert 37 < len(scans) / info.duration_s < 43  # ~40 Hz
    assert 47 < len(odoms) / info.duration_s < 53  # ~50 Hz

    s = scans[0].msg
    assert len(s.ranges) == 1081 and len(s.intensities) == 1081
    assert s.header.frame_id == "laser"
    assert s.angle_min == pytest.approx(-2.356, abs=1e-3) and s.angle_max == pytest.approx(2.356, abs=1e-3)
    assert s.angle_increment == pytest.approx(np.radians(0.25), rel=1e-4)
    assert s.range_max == pytest.approx(30.0)
    stamps = [stamp_to_ns(m.msg.header.stamp) for m in scans]
    assert all(a < b for a, b in zip(stamps, stamps[1:]))
    o = odoms[0].msg
    assert (o.header.frame_id, o.child_frame_id) == ("odom", "base_link")


def test_real_ros1_scan_raw_cdr_is_ros2_laserscan(bag3):
    ts = jazzy_typestore()
    scan = next(read_messages(bag3, ["/scan"]))
    assert scan.is_ros1 and hasattr(scan.msg.header, "seq")  # ROS 1 layout when deserialized
    ros2 = ts.deserialize_cdr(scan.raw_cdr, "sensor_msgs/msg/LaserScan")
    np.testing.assert_array_equal(ros2.ranges, scan.msg.ranges)
    np.testing.assert_array_equal(ros2.intensities, scan.msg.intensities)
    assert ros2.header.frame_id == "laser"
    assert stamp_to_ns(ros2.header.stamp) == stamp_to_ns(scan.msg.header.stamp)
    assert ros2.angle_increment == scan.msg.angle_increment

    odom = next(read_messages(bag3, ["/vesc/odom"]))
    ros2_odom = ts.deserialize_cdr(odom.raw_cdr, "nav_msgs/msg/Odometry")
    assert ros2_odom.child_frame_id == "base_link"
    assert ros2_odom.pose.pose.position.x == odom.msg.pose.pose.position.x
    np.testing.assert_array_equal(ros2_odom.pose.covariance, odom.msg.pose.covariance)


def test_real_ros1_raw_cdr_deserializes_with_rclpy(bag3):
    serialization = pytest.importorskip("rclpy.serialization")
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    scan = next(read_messages(bag3, ["/scan"]))
    msg = serialization.deserialize_message(scan.raw_cdr, sensor_msgs.LaserScan)
    np.testing.assert_array_equal(np.asarray(msg.ranges, dtype=np.float32), scan.msg.ranges)
    assert msg.header.stamp.sec == scan.msg.header.stamp.sec


# ------------------------------------------------------------------ TF: odometry and the laser mount


def _tf_odometry_bag(path: Path, laser_quaternion, twists, dt: float = 0.1) -> np.ndarray:
    """A bag with odometry only as /tf odom -> base_footprint -> base_link (the footprint edge
    static) driven by ``twists`` held dt each, and /tf_static base_link -> laser rotated by
    ``laser_quaternion``; returns the stamps (s) and the poses of base_link written."""
    from localization.core.geometry import integrate_twist
    poses = [np.zeros(3)]
    for v in twists:
        poses.append(compose(poses[-1], integrate_twist(*v, dt)))
    with BagWriter(path) as w:
        ts = w.typestore
        w.add_topic("/tf_static", "tf2_msgs/msg/TFMessage")
        w.add_topic("/tf", "tf2_msgs/msg/TFMessage")
        w.add_topic("/scan", "sensor_msgs/msg/LaserScan")
        w.write("/tf_static", T0, make_tf_message(ts, [
            make_transform_stamped(ts, T0, "base_link", "laser", x=0.14, y=0.02, z=0.3, quaternion=laser_quaternion),
            make_transform_stamped(ts, T0, "base_footprint", "base_link", z=0.05)]))
        for k, p in enumerate(poses):
            t = T0 + int(k * dt * 1e9)
            w.write("/tf", t + 3_000_000, make_tf_message(ts, [make_transform_stamped(ts, t, "/odom", "/base_footprint",
                                                                                      x=p[0], y=p[1], yaw=p[2])]))
        w.write("/scan", T0 + 1_000_000, make_laser_scan(ts, T0, "laser", np.ones(10), angle_min=-1.0, angle_max=1.0,
                                                         angle_increment=2.0 / 9, range_min=0.1, range_max=5.0))
    return np.asarray(poses)


def test_odometry_from_tf_inverts_the_integration_exactly(tmp_path):
    """No Odometry topic: bags.tf differentiates odom -> base_link (through a static footprint edge,
    ROS 1 style leading slashes) into twists at the TF rate; integrating them gives the poses back."""
    from localization.eval.datasets import bag_odometry
    from localization.eval.reference import dead_reckon
    rng = np.random.default_rng(2)
    twists = np.column_stack([rng.uniform(0.0, 0.6, 40), np.zeros(40), rng.uniform(-1.5, 1.5, 40)])
    twists[5] = (0.0, 0.0, 0.0)  # standing
    twists[9] = (0.0, 0.0, 1.2)  # a turn on the spot
    path = tmp_path / "tf_odom"
    poses = _tf_odometry_bag(path, (0.0, 0.0, 0.0, 1.0), twists)
    odo = bag_odometry(path, "/odom")
    assert odo.source == "/tf odom -> base_link" and len(odo.messages) == len(poses)
    t, tw = odo.arrays()
    np.testing.assert_allclose(t - t[0], np.arange(len(poses)) * 0.1, atol=3e-7)  # float s at 1.7e9 s: 2.4e-7
    np.testing.assert_allclose(tw[1:], twists, atol=1e-5)  # the stamps' rounding, relative to dt = 0.1 s
    np.testing.assert_allclose(dead_reckon(t, tw, t), poses, atol=1e-9)  # integrated over the same stamps: exact
    assert np.all(odo.record_ns - np.round(t * 1e9).astype(np.int64) == 3_000_000)  # each from its TF message


@pytest.mark.parametrize("quaternion, yaw, upright", [
    ((0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)), np.pi / 2, True),  # turned 90 deg left
    ((1.0, 0.0, 0.0, 0.0), 0.0, False),  # upside down (roll pi): x still forward, the scan mirrored
    ((0.0, np.sin(0.05), 0.0, np.cos(0.05)), 0.0, True),  # pitched down 0.1 rad
])
def test_laser_mount_from_tf_static(tmp_path, quaternion, yaw, upright):
    from localization.bags import laser_mount_from_bag
    from localization.eval.datasets import bag_laser_mount
    path = tmp_path / "mount"
    _tf_odometry_bag(path, quaternion, np.zeros((3, 3)))
    mount = laser_mount_from_bag(path, "/scan")
    assert mount is not None and mount.upright == upright and mount.frames == ("base_link", "laser")
    np.testing.assert_allclose(mount.pose, (0.14, 0.02, yaw), atol=1e-9)
    lines = []
    assert bag_laser_mount(path, "/scan", (0.275, 0.0, 0.0), log=lines.append) == pytest.approx((0.14, 0.02, yaw))
    assert "from the bag's TF" in lines[0] and (upright or "upside down" in lines[-1])
    # without the transform: the fallback, said in one line
    assert laser_mount_from_bag(path, "/scan", base_frame="chassis") is None
    lines = []
    assert bag_laser_mount(path, "/scan", (0.275, 0.0, 0.0), base_frame="chassis", log=lines.append) == (0.275, 0, 0)
    assert len(lines) == 1 and "laser_offset_" in lines[0]


def test_bag_without_odometry_is_one_clear_error(tmp_path):
    from localization.eval.datasets import bag_odometry
    path = tmp_path / "no_odom"
    with BagWriter(path) as w:
        ts = w.typestore
        w.write("/scan", T0, make_laser_scan(ts, T0, "laser", np.ones(10), angle_min=-1.0, angle_max=1.0,
                                             angle_increment=2.0 / 9, range_min=0.1, range_max=5.0))
    with pytest.raises(BagError, match="no odometry in bag .*no nav_msgs/msg/Odometry on /odom and no TF chain"):
        bag_odometry(path, "/odom")


def test_real_pioneer_bag_odometry_only_in_tf():
    """lgfloor2 (2011): no Odometry topic; its /tf (ROS 1 tf/tfMessage, '/odom' -> '/base_link') gives
    the twist stream at 10 Hz, and /tf carries the laser 0.135 m ahead of base_link."""
    from localization.bags import laser_mount_from_bag
    from localization.eval.datasets import bag_odometry, real_bag_path
    path = real_bag_path("lgfloor2")
    odo = bag_odometry(path, "/odom")
    t, tw = odo.arrays()
    assert odo.source == "/tf odom -> base_link" and len(t) > 1500
    assert np.all(np.diff(t) > 0) and np.median(np.diff(t)) == pytest.approx(0.1, abs=0.005)
    assert np.percentile(np.abs(tw[:, 0]), 99) < 0.7 and np.abs(tw[:, 1]).max() < 0.05  # a differential base
    mount = laser_mount_from_bag(path, "/base_scan")
    assert mount.pose == pytest.approx((0.135, 0.0, 0.0), abs=1e-6) and mount.upright
