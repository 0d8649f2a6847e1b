"""Small builders shared by the tests (synthetic maps and messages)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from localization.core.occupancy_map import OccupancyMap


def corridor_map(width_cells=200, height_cells=60, wall_rows=(10, 50), resolution=0.05, origin=(0.0, 0.0, 0.0)):
    """A horizontal corridor: free between two occupied wall rows, closed at both ends."""
    data = np.full((height_cells, width_cells), -1, dtype=np.int8)
    lo, hi = wall_rows
    data[lo + 1:hi, 1:-1] = 0
    data[lo, :] = 100
    data[hi, :] = 100
    data[lo:hi + 1, 0] = 100
    data[lo:hi + 1, -1] = 100
    return OccupancyMap(data, resolution, origin)


def occupancy_grid_msg(occupancy_map: OccupancyMap):
    """A duck-typed nav_msgs/OccupancyGrid for an OccupancyMap."""
    x, y, yaw = occupancy_map.origin
    q = SimpleNamespace(x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2))
    info = SimpleNamespace(width=occupancy_map.width, height=occupancy_map.height, resolution=occupancy_map.resolution,
                           origin=SimpleNamespace(position=SimpleNamespace(x=x, y=y, z=0.0), orientation=q))
    return SimpleNamespace(header=SimpleNamespace(frame_id="map"), info=info, data=occupancy_map.data.ravel().tolist())


def localize_recording(rec, params, occupancy_map):
    """A simulated recording through a Localizer from its /initialpose: (FeedLog, truth comparison)."""
    from localization.core.localizer import Localizer
    from localization.eval.feed import Feeder, recording_events
    from localization.eval.metrics import compare_to_truth

    loc = Localizer(params)
    loc.set_map(occupancy_map)
    loc.set_initial_pose(rec.initial_pose, stamp=-0.001)
    feeder = Feeder(loc)
    feeder.feed(recording_events(rec))
    t, poses = feeder.log.estimates()
    return feeder.log, compare_to_truth(t, poses, rec.truth_t, rec.truth_poses)


def wrap_sensor_updates(pf, wrap) -> None:
    """Replace a filter's sensor update by ``wrap(update)`` (the plain and the tempered first update after
    an initial pose are one call), so a test that blocks or counts updates sees every one."""
    pf.sensor_update = wrap(pf.sensor_update)
