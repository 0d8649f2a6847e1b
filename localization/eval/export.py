"""A replay's run as an MCAP bag (rosbag2, written with rosbags): open it in Foxglove Studio, or
play it into RViz with ``ros2 bag play OUT/run_mcap`` (rviz/localization.rviz shows every topic).

    localization-replay BAG --map basement_fixed --params real_params --mcap   # writes OUT/run_mcap/
    localization-replay BAG --map basement_fixed --params real_params          # does not

(To watch a replay as it runs instead: ``localization-replay ... --foxglove``, ``localization.ros.live_view``.)

Topics (stamps = bag time of the data):

    /map                 nav_msgs/OccupancyGrid       once, latched (transient local)
    /scan                sensor_msgs/LaserScan        every scan fed to the filter, in its own frame
    /pf/particles        geometry_msgs/PoseArray      the cloud after a sensor update (≤ max_particles,
                                                      at most every ``cloud_period`` s)
    /pf/pose/odom        nav_msgs/Odometry            every published estimate
    /pf/track            nav_msgs/Path                the estimated track so far, every ``track_period`` s
    /truth/track         nav_msgs/Path                the ground truth track (when the bag has one)
    /reference/track     nav_msgs/Path                the scan-matched reference track (when computed)
    /tf                  tf2_msgs/TFMessage           map -> base_link_pf at each estimate
    /tf_static           tf2_msgs/TFMessage           base_link_pf -> the scan's frame (laser offset)

``ReplayRecorder`` is the hook ``run_replay`` calls after each scan (``ReplayOptions.on_scan``):
it keeps the scans and thinned clouds in memory (a few MB per minute of bag).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from localization.bags import (
    BagError,
    BagWriter,
    make_header,
    make_laser_scan,
    make_odometry,
    make_pose,
    make_tf_message,
    make_transform_stamped,
)

ESTIMATE_FRAME = "base_link_pf"
MAX_PARTICLES = 300
CLOUD_PERIOD_S = 0.1
TRACK_PERIOD_S = 1.0
PATH_SPACING_S = 0.1


def _ns(t: float) -> int:
    return max(0, int(round(float(t) * 1e9)))


@dataclass
class ReplayRecorder:
    """Collects what the export needs while ``run_replay`` runs (``__call__(scan, localizer)``)."""

    max_particles: int = MAX_PARTICLES
    cloud_period: float = CLOUD_PERIOD_S
    scans: list = field(default_factory=list)  # ScanData
    clouds: list = field(default_factory=list)  # (t, (K, 3))
    _last_cloud: float = -np.inf

    def __call__(self, scan, localizer) -> None:
        self.scans.append(scan)
        if localizer.ready and scan.stamp - self._last_cloud >= self.cloud_period:
            p = np.asarray(localizer.particles(), dtype=float)
            p = p[np.all(np.isfinite(p), axis=1)]
            if len(p) > self.max_particles:
                p = p[np.linspace(0, len(p) - 1, self.max_particles).round().astype(np.intp)]
            self.clouds.append((float(scan.stamp), p.copy()))
            self._last_cloud = scan.stamp


def _path(w, t_ns, frame, t, poses):
    T = w.typestore.types
    stamped = [T["geometry_msgs/msg/PoseStamped"](header=make_header(w.typestore, _ns(ti), frame),
                                                  pose=make_pose(w.typestore, *p)) for ti, p in zip(t, poses)
               if np.all(np.isfinite(p))]
    return T["nav_msgs/msg/Path"](header=make_header(w.typestore, t_ns, frame), poses=stamped)


def _grid(w, occupancy_map, t_ns, frame):
    T = w.typestore.types
    ox, oy, oyaw = (float(v) for v in occupancy_map.origin)
    info = T["nav_msgs/msg/MapMetaData"](
        map_load_time=make_header(w.typestore, t_ns, frame).stamp, resolution=float(occupancy_map.resolution),
        width=int(occupancy_map.width), height=int(occupancy_map.height), origin=make_pose(w.typestore, ox, oy, oyaw))
    data = np.ascontiguousarray(occupancy_map.data, dtype=np.int8).ravel()
    return T["nav_msgs/msg/OccupancyGrid"](header=make_header(w.typestore, t_ns, frame), info=info, data=data)


def write_run_mcap(path, res, recorder: ReplayRecorder, map_frame: str = "map",
                   track_period: float = TRACK_PERIOD_S) -> Path:
    """Write the replay ``res`` (a ``ReplayResult``) and what ``recorder`` kept to an MCAP rosbag2
    bag at ``path`` (a new folder holding ``<name>_0.mcap`` and ``metadata.yaml``). Raises BagError."""
    path = Path(path)
    params = res.options.params
    offset = (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw)
    est_t, est_poses = np.asarray(res.est_t, dtype=float), np.asarray(res.est_poses, dtype=float).reshape(-1, 3)
    times = [s.stamp for s in recorder.scans] + list(est_t)
    t0 = min(times) if times else 0.0
    with BagWriter(path, storage="mcap", overwrite=True) as w:
        T = w.typestore.types
        w.add_topic("/map", "nav_msgs/msg/OccupancyGrid", qos="latched")
        w.add_topic("/tf_static", "tf2_msgs/msg/TFMessage", qos="latched")
        w.write("/map", _ns(t0), _grid(w, res.occupancy_map, _ns(t0), map_frame))
        frames = sorted({s.frame_id or "laser" for s in recorder.scans}) or ["laser"]
        w.write("/tf_static", _ns(t0), make_tf_message(w.typestore, [
            make_transform_stamped(w.typestore, _ns(t0), ESTIMATE_FRAME, f, offset[0], offset[1], 0.0, offset[2])
            for f in frames]))
        events = []  # (t_ns, order, topic, builder)
        for s in recorder.scans:
            events.append((_ns(s.stamp), 0, "/scan", s))
        for t, cloud in recorder.clouds:
            events.append((_ns(t), 1, "/pf/particles", cloud))
        for t, pose in zip(est_t, est_poses):
            if np.all(np.isfinite(pose)):
                events.append((_ns(t), 2, "/pf/pose/odom", pose))
        tracks = [("/pf/track", est_t, est_poses)]
        if res.has_truth:
            tracks.append(("/truth/track", np.asarray(res.truth_t), np.asarray(res.truth_poses).reshape(-1, 3)))
        ref = getattr(res, "reference", None)
        if ref is not None:
            rt, rp = ref.good_track()
            tracks.append(("/reference/track", np.asarray(rt), np.asarray(rp).reshape(-1, 3)))
        for topic, tt, pp in tracks:
            if len(tt) == 0:
                continue
            thin = np.concatenate([[True], np.diff(np.floor(tt / PATH_SPACING_S)) > 0])  # ≤ 10 poses/s in a Path
            tt, pp = tt[thin], pp[thin]
            marks = np.arange(tt[0], tt[-1] + track_period, track_period)
            for m in marks:
                events.append((_ns(min(m, tt[-1])), 3, topic, (tt, pp, m)))
        events.sort(key=lambda e: (e[0], e[1]))
        for t_ns, _, topic, item in events:
            if topic == "/scan":
                s = item
                w.write(topic, t_ns, make_laser_scan(
                    w.typestore, t_ns, s.frame_id or "laser", s.ranges, angle_min=s.angle_min,
                    angle_max=s.angle_max, angle_increment=s.angle_increment, range_min=s.range_min,
                    range_max=s.range_max, time_increment=s.time_increment, scan_time=s.scan_time))
            elif topic == "/pf/particles":
                w.write(topic, t_ns, T["geometry_msgs/msg/PoseArray"](
                    header=make_header(w.typestore, t_ns, map_frame), poses=[make_pose(w.typestore, *p) for p in item]))
            elif topic == "/pf/pose/odom":
                x, y, yaw = item
                w.write(topic, t_ns, make_odometry(w.typestore, t_ns, map_frame, ESTIMATE_FRAME, x, y, yaw))
                w.write("/tf", t_ns, make_tf_message(w.typestore, [
                    make_transform_stamped(w.typestore, t_ns, map_frame, ESTIMATE_FRAME, x, y, 0.0, yaw)]))
            else:
                tt, pp, m = item
                keep = tt <= m + 1e-9
                w.write(topic, t_ns, _path(w, t_ns, map_frame, tt[keep], pp[keep]))
    return path


__all__ = ["BagError", "ReplayRecorder", "write_run_mcap"]
