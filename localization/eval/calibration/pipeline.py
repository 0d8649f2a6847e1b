"""Calibration from scans, odometry and a map, or from a bag (``localization.eval.calibration``): the
yardstick (step 1), the range model on its matches (step 2), the yardstick again with the fitted range
model when it moves endpoints, then the odometry and the mount (steps 3–4)."""
from __future__ import annotations

import numpy as np

from localization.core.geometry import compose, wrap_angle
from localization.core.matching import MatcherConfig
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import clean_ranges
from localization.eval.calibration.odometry import fit_odometry
from localization.eval.calibration.range_model import fit_range_model
from localization.eval.calibration.result import KEYS, CalibrationError, CalibrationResult
from localization.eval.calibration.stamps import check_scan_stamps
from localization.eval.reference import ReferenceTrack, build_reference, read_odometry, read_scans


def _matched_laser(ref: ReferenceTrack, mount):
    """Times and laser poses of the accepted scan-to-map matches (no odometry in them)."""
    ok = ref.accepted & np.all(np.isfinite(ref.matched), axis=1)
    return ref.t[ok], compose(ref.matched[ok], np.asarray(mount, dtype=float)), ok


def calibrate(scans, odom_t, twist, occupancy_map: OccupancyMap, initial_pose, mount0=(0.275, 0.0, 0.0),
              config: MatcherConfig | None = None, log=None, scan_stamp: str = "first_beam",
              scan_stamp_offset: float = 0.0) -> CalibrationResult:
    """Calibrate from scans (``ScanData``), odometry (stamps, twists (M, 3)) and a map (package doc);
    ``initial_pose`` None: the yardstick starts with a global match."""
    say = log or (lambda *_: None)
    if len(scans) < 20:
        raise CalibrationError(f"only {len(scans)} scans: too few to calibrate")
    if len(odom_t) < 10:
        raise CalibrationError(f"only {len(odom_t)} odometry messages: too few to calibrate")
    odom = (np.asarray(odom_t, dtype=float), np.asarray(twist, dtype=float).reshape(-1, 3))
    say(f"reference track of {len(scans)} scans ...")
    kw = {"config": config, "scan_stamp": scan_stamp, "scan_stamp_offset": scan_stamp_offset, "log": log}
    ref = build_reference(scans, occupancy_map, mount0, odom, initial_pose, **kw)
    if ref.counts.get("accepted", 0) < 20:
        raise CalibrationError(f"only {ref.counts.get('accepted', 0)} of {len(scans)} scans matched the map: check "
                               "the map, --initial-pose and the laser mount")
    lt, lp, ok = _matched_laser(ref, mount0)
    pinned = ok & np.all(ref.constrained[:, :3], axis=1)
    s, s_sig, o, o_sig, n_s = fit_range_model(occupancy_map, scans, compose(np.where(ok[:, None], ref.matched, 0.0),
                                                                            np.asarray(mount0, dtype=float)), pinned)
    median_range = _median_range(scans)
    say(f"range scale {s:.5f} ± {s_sig:.5f}, wall surface {100 * o:.2f} ± {100 * o_sig:.2f} cm behind the "
        f"free-space edge ({n_s} scans)")
    depth = float(np.clip(o, 0.0, 0.5))  # map_wall_depth's range: a return never ends before the edge
    if abs(s - 1.0) * median_range + depth > 0.25 * occupancy_map.resolution:
        say("matching again with the range scale and the wall surface ...")
        ref = build_reference(scans, occupancy_map, mount0, odom, initial_pose, range_scale=s,
                              wall_depth=depth, **kw)
        lt, lp, ok = _matched_laser(ref, mount0)
    say(f"fitting odometry and mount on {len(lt)} matched scans ...")
    start = (ref.odometry.get("time_offset_s", 0.0), ref.odometry.get("speed_scale", 1.0))
    x, sig, pairs, rms, rejected, channels = fit_odometry(lt, lp, odom[0], odom[1], mount0, start=start, log=log)
    values = dict(zip(KEYS[:7], (float(v) for v in x)))
    values["laser_offset_yaw"] = float(wrap_angle(values["laser_offset_yaw"]))
    values["lidar_scale_to_map_scale"] = s
    values["map_wall_depth"] = depth
    unc = dict(zip(KEYS[:7], (float(v) for v in sig)))
    unc["lidar_scale_to_map_scale"] = s_sig
    unc["map_wall_depth"] = o_sig
    return CalibrationResult(values=values, uncertainty=unc, scans=len(scans), good_scans=int(ok.sum()),
                             pairs=pairs, residual_rms=rms, rejected=rejected, channel_offsets=channels,
                             wall_surface={"offset_m": o, "sigma_m": o_sig}, yardstick=ref.summary())


def _median_range(scans) -> float:
    sample = scans[:: max(1, len(scans) // 50)]
    r = np.concatenate([clean_ranges(s.ranges, s.range_min, s.range_max) for s in sample])
    r = r[np.isfinite(r)]
    return float(np.median(r)) if r.size else 1.0


def calibrate_bag(bag_path, occupancy_map: OccupancyMap, scan_topic: str = "/scan", odom_topic: str = "/odom",
                  initial_pose=None, mount0=(0.275, 0.0, 0.0), config: MatcherConfig | None = None,
                  log=None, *, scan_stamp: str = "first_beam", scan_stamp_offset: float = 0.0,
                  odom_frame: str = "odom", base_frame: str = "base_link") -> CalibrationResult:
    """``calibrate`` on a bag: scans on ``scan_topic``, odometry on ``odom_topic`` (else TF
    ``odom_frame → base_frame``); start pose ``initial_pose``, else the bag's /initialpose, else a
    global match. The scan stamp convention is checked against the bag's record times (a log line)."""
    say = log or (lambda *_: None)
    scans = read_scans(bag_path, scan_topic)
    odom_t, twist = read_odometry(bag_path, odom_topic, odom_frame, base_frame)
    if initial_pose is None:
        initial_pose = initial_pose_from_bag(bag_path)
    if initial_pose is None:
        say("no start pose (--initial-pose, /initialpose): the reference track starts with a global match")
    try:
        check = check_scan_stamps(bag_path, scan_topic)
        say(check.message(scan_stamp))
    except ValueError:
        pass
    return calibrate(scans, odom_t, twist, occupancy_map, initial_pose, mount0, config, log, scan_stamp,
                     scan_stamp_offset)


def initial_pose_from_bag(bag_path, topic: str = "/initialpose"):
    """The first /initialpose (PoseWithCovarianceStamped) of the bag, or None."""
    from localization.bags import open_bag
    from localization.ros.conversions import pose_from_pose_with_covariance
    with open_bag(bag_path) as bag:
        info = bag.topic_infos.get(topic)
        if info is None or info.msgtype != "geometry_msgs/msg/PoseWithCovarianceStamped":
            return None
        for m in bag.messages([topic]):
            return np.asarray(pose_from_pose_with_covariance(m.msg).pose, dtype=float)
    return None
