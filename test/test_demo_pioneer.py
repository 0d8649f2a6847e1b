"""The demo's Pioneer figures from a replay result (no bag needed)."""
from types import SimpleNamespace

import numpy as np

from localization.core.parameters import Parameters
from localization.tools.demo import END_WINDOW_S, Job, Result, pioneer_metrics, pioneer_table


def _result(agreement_t, agreement, refused=3):
    est_t = np.arange(0.0, 30.0, 0.1)
    poses = np.column_stack([0.01 * np.arange(est_t.size), np.zeros(est_t.size), np.zeros(est_t.size)])
    return SimpleNamespace(options=SimpleNamespace(params=Parameters()), init_t=0.0, scan_t=est_t, est_t=est_t,
                           est_poses=poses, counts={"recoveries": 1, "refused_jumps": refused}, reference=None,
                           agreement_t=np.asarray(agreement_t), agreement=np.asarray(agreement),
                           health=np.full(est_t.size, 0.9))


def test_end_agreement_is_the_median_over_the_last_seconds_and_undone_updates_are_counted():
    t = np.arange(0.0, 30.0, 0.1)
    a = np.where(t < t[-1] - END_WINDOW_S, 0.2, 0.95)  # lost in the middle, fits the map at the end
    m = pioneer_metrics(_result(t, a))
    assert m["end_agreement_median"] == 0.95 and m["refused_jumps"] == 3 and m["recoveries"] == 1
    m = pioneer_metrics(_result(t, np.where(t < t[-1] - END_WINDOW_S, 0.95, 0.3)))
    assert m["end_agreement_median"] == 0.3  # ends where the scans do not fit
    row = pioneer_table([Result(Job("bag", "pioneer", "lgfloor", "pioneer_params.yaml"),
                                {"initial_pose_source": "global", "pioneer": m})])
    assert "0.300" in row and "undone" in row and "end agr" in row
