"""Where the node's first pose comes from, and the estimate kept for the next start.

At configuration (``initial_pose_at_start``): nav2-style ``set_initial_pose`` with ``initial_pose.x/.y/.yaw``;
else, with ``persist_pose`` (opt-in) and no ``global_localization``, the pose the last run persisted
(``core.pose_store``, in the map frame); else nothing: the node waits for /initialpose.

While it runs (``PosePersistence.save``, every ``persist_pose_period`` s and at shutdown): the
estimate and its covariance, written atomically, when it changed since the last write.
"""
from __future__ import annotations

import numpy as np

from localization.core import pose_store


def initial_pose_at_start(params, localizer, log) -> None:
    """Give ``localizer`` the start pose of the parameters, else the persisted one (module docstring)."""
    p = params
    if p.set_initial_pose:
        pose = np.array([p["initial_pose.x"], p["initial_pose.y"], p["initial_pose.yaw"]])
        if localizer.set_initial_pose(pose, None, 0.0):
            log.info(f"initial pose from parameters ({pose[0]:.2f}, {pose[1]:.2f}, {pose[2]:.2f}): localizing "
                     "once a map arrives")
        return
    if not p.persist_pose or p.global_localization:
        return
    path = pose_store.pose_file(p.persist_pose_file)
    stored, why = pose_store.load_pose(path)
    if stored is None:
        log.info(f"{why}: waiting for an initial pose")
        return
    if stored.frame_id not in ("", p.map_frame):
        log.warning(f"persisted pose {path} is in frame {stored.frame_id!r}, not {p.map_frame!r}: ignored")
        return
    if localizer.set_initial_pose(stored.pose, stored.covariance, 0.0):
        x, y, th = stored.pose
        log.info(f"initial pose from the persisted pose {path} ({x:.2f}, {y:.2f}, {th:.2f})")


class PosePersistence:
    """Writes the localizer's estimate to ``persist_pose_file`` when it changed (``persist_pose``)."""

    def __init__(self, params, log):
        self.params, self.log = params, log
        self._last = None  # (stamp, rounded pose) of the last write

    def save(self, localizer) -> None:
        est = localizer.estimate if localizer is not None else None
        if est is None or not localizer.ready:
            return
        key = (float(est.stamp), *np.round(est.pose, 4))
        if key == self._last:
            return
        path = pose_store.pose_file(self.params.persist_pose_file)
        try:
            if pose_store.save_pose(path, est.pose, est.covariance, self.params.map_frame, est.stamp):
                self._last = key
        except OSError as exc:
            self.log.warning(f"could not persist the pose to {path}: {exc}", throttle_duration_sec=30.0)
