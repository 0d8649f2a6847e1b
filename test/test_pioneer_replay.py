"""The Pioneer's trace0 end to end (a real robot in a building that changed since its map).

After ~60 s the scans stop fitting the 2011 map where the robot is: the filter holds on odometry,
and a challenger later wins where the scans fit again, metres from the held pose. What must hold
on the real bag, whatever the seed: the published pose never jumps (the switch glides), and the
bag ends where the scans fit the map (docs/replay.md, "What the yardstick cannot see").
"""
from __future__ import annotations

import numpy as np
import pytest

from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.datasets import real_bag, real_bag_path
from localization.eval.replay import ReplayOptions, run_replay

JUMP_M = 0.5  # m: the largest step between consecutive published estimates once started
END_S = 10.0  # s: the bag's last seconds, scored by scan-map agreement


@pytest.mark.parametrize("seed", [0, 1])
def test_trace0_never_jumps_and_ends_where_the_scans_fit(seed):
    rb = real_bag("trace0")
    params = Parameters.from_yaml(config_dir() / rb.params, random_seed=seed, scan_stamp=rb.scan_stamp)
    res = run_replay(ReplayOptions(real_bag_path(rb.name), rb.map, params, rb.start, label=rb.name,
                                   scan_topic=rb.scan_topic, odom_topic=rb.odom_topic, reference=False,
                                   log=lambda line: None))
    assert res.counts["recoveries"] >= 1  # the building changed: a switch happened ...
    t, poses = res.est_t, res.est_poses
    assert np.isfinite(poses).all()
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    started = t[1:] > t[0] + 1.0
    assert steps[started].max() <= JUMP_M  # ... and was published without a jump
    end = res.agreement_t > res.agreement_t[-1] - END_S
    assert np.median(res.agreement[end]) >= 0.9  # the bag ends where the scans fit (a lost filter: ~0.5)
