"""The correlative scan matcher and the reference track (issue 10, parts 1 and 4): kernels equal
their numpy references, branch and bound equals the exhaustive search, the reference track
follows the simulator's ground truth, a featureless corridor is flagged ambiguous, the
along-/cross-track decomposition and the lag on hand-made tracks, and localization-replay's
reference figures."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from localization.core.geometry import compose
from localization.core.matching import CorrelativeMatcher, MatcherConfig
from localization.core.matching import kernels as K
from localization.core.matching.grids import max_pool
from localization.core.occupancy_map import OccupancyMap, load_map
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData
from localization.eval.datasets import REAL_BAGS, real_bag_path, sim_bag, trial_config
from localization.eval.metrics import interpolate_poses
from localization.eval.reference import (
    best_lag,
    build_reference,
    dead_reckon,
    lag_from_along,
    track_errors,
)
from localization.sim import simulate

# ------------------------------------------------------------------ kernels


def test_score_kernel_equals_numpy_reference():
    rng = np.random.default_rng(0)
    grid = rng.random((80, 90)).astype(np.float32)
    cols = rng.integers(-5, 95, (7, 300)).astype(np.int64)
    rows = rng.integers(-5, 85, (7, 300)).astype(np.int64)
    cj = rng.integers(0, 7, 500).astype(np.int64)
    cu = rng.integers(-6, 7, 500).astype(np.int64)
    cv = rng.integers(-6, 7, 500).astype(np.int64)
    fast = K.score_candidates(grid, cols, rows, cj, cu, cv)
    ref = K.score_candidates_numpy(grid, cols, rows, cj, cu, cv)
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12)


def test_max_pool_bounds_every_cell_of_its_block():
    rng = np.random.default_rng(1)
    g = rng.random((23, 31))
    P = max_pool(g, 4)
    for r, c in ((0, 0), (5, 7), (22, 30), (20, 28)):
        assert P[r, c] == g[r:r + 4, c:c + 4].max()


def test_branch_and_bound_equals_exhaustive_search():
    m = load_map("stata_basement")
    matcher = CorrelativeMatcher(m)
    cfg = trial_config("trial1_noise0")
    caster = ExactRayCaster(m, 10.0)
    angles = np.linspace(cfg.angle_min, cfg.angle_max, 1081)
    truth = np.array(cfg.start, dtype=float)
    ranges = caster.cast(compose(truth, (0.275, 0.0, 0.0))[None], angles)[0]
    q = np.stack([0.275 + ranges * np.cos(angles), ranges * np.sin(angles)], 1) / m.resolution
    g0 = m.world_to_grid_pose(truth + [0.13, -0.08, 0.03])
    phis = g0[2] + np.arange(-8, 9) * 0.006
    cols, rows = matcher._cells(g0, phis, q)
    k, W = 4, 8
    starts = np.arange(-W, W + 1, k)
    jj, uu, vv = (a.ravel().astype(np.int64) for a in np.meshgrid(np.arange(len(phis)), starts, starts,
                                                                     indexing="ij"))
    bounds = K.score_candidates(matcher.P, cols, rows, jj, uu, vv)
    order = np.argsort(-bounds, kind="stable")
    args = (matcher.L, cols, rows, jj[order], uu[order], vv[order], bounds[order], k, W)
    fast = K.branch_and_bound(*args)
    ref = K.branch_and_bound_numpy(*args)
    assert fast[0] == pytest.approx(ref[0], abs=1e-12)
    assert tuple(fast[1:]) == tuple(ref[1:])
    # the coarse bounds really bound: every block's bound >= the best fine score inside it
    assert bounds.max() >= fast[0]


# ------------------------------------------------------------------ the matcher


def _corridor(length_cells: int, junction: bool) -> OccupancyMap:
    """A straight corridor 2 m wide (0.05 m cells), optionally with a side opening mid-way."""
    h = 80
    data = np.full((h, length_cells), 100, dtype=np.int8)
    data[20:60, 1:-1] = 0
    if junction:
        c = length_cells // 2
        data[60:h - 1, c - 20:c + 20] = 0  # a side corridor 2 m wide going up
    return OccupancyMap(data, 0.05, (0.0, 0.0, 0.0))


@pytest.mark.parametrize("junction", [False, True])
def test_featureless_corridor_is_ambiguous(junction):
    m = _corridor(1200, junction)  # 60 m long: the 10 m lidar sees neither end
    matcher = CorrelativeMatcher(m, MatcherConfig(max_range=10.0))
    angles = np.linspace(-0.75 * np.pi, 0.75 * np.pi, 1081)
    truth = np.array([30.0, 2.0, 0.0])
    ranges = ExactRayCaster(m, 10.0).cast(compose(truth, (0.275, 0.0, 0.0))[None], angles)[0]
    ranges = np.where(ranges >= 10.0, np.inf, ranges)
    r = matcher.match(ranges, angles, (0.275, 0.0, 0.0), truth + [0.1, 0.05, 0.02])
    assert r is not None
    # across the corridor and in heading the match is exact either way
    assert abs(r.pose[1] - truth[1]) < 0.01 and abs(r.pose[2]) < 0.005
    assert r.ambiguous == (not junction), (r.std_xy_max, r.covariance)
    if junction:
        assert np.hypot(*(r.pose[:2] - truth[:2])) < 0.01
    else:
        assert r.covariance[0, 0] > 10 * r.covariance[1, 1]  # uncertain along the corridor only


@pytest.fixture(scope="module")
def trial1():
    cfg = trial_config("trial1_noise0", duration=6.0)
    m = load_map(cfg.map)
    return cfg, m, simulate(cfg, m)


def _scans(cfg, rec):
    return [ScanData(float(t), r, cfg.angle_min, cfg.angle_max, rec.scan_angle_increment, cfg.range_min,
                     cfg.range_max, rec.scan_time_increment) for t, r in zip(rec.scan_t, rec.scan_ranges)]


def test_reference_track_follows_ground_truth(trial1):
    cfg, m, rec = trial1
    # seeded only by the initial pose (0.5 m off) and the previous match carried forward
    ref = build_reference(_scans(cfg, rec), m, cfg.laser_offset, initial_pose=rec.initial_pose)
    truth = interpolate_poses(ref.t, rec.truth_t, rec.truth_poses)
    good = ref.good
    assert good.mean() > 0.9, ref.counts
    err = np.hypot(*(ref.poses[good, :2] - truth[good, :2]).T)
    assert np.median(err) < 0.02, np.median(err)
    assert np.percentile(err, 95) < 0.05


def test_reference_track_seeded_by_an_estimate_track(trial1):
    cfg, m, rec = trial1
    # a lagging, offset "filter": the reference must not follow it
    est_t = rec.truth_t
    est = interpolate_poses(est_t - 0.05, rec.truth_t, rec.truth_poses)
    est[:, 1] += 0.1
    ok = np.all(np.isfinite(est), axis=1)
    ref = build_reference(_scans(cfg, rec)[:80], m, cfg.laser_offset, est_t[ok], est[ok])
    truth = interpolate_poses(ref.t, rec.truth_t, rec.truth_poses)
    err = np.hypot(*(ref.poses[ref.good, :2] - truth[ref.good, :2]).T)
    assert ref.good.sum() > 70 and np.median(err) < 0.02


def test_reference_track_deskews_a_fast_sweeping_scan():
    """The fast trial (up to 7 m/s, 18.75 ms sweep: the scan smeared over 0.13 m): deskewed
    along the track's own motion the reference stays at the millimetre level."""
    cfg = trial_config("fast", duration=5.0)
    m = load_map(cfg.map)
    rec = simulate(cfg, m)
    assert rec.scan_time_increment > 0
    scans = _scans(cfg, rec)
    medians = {}
    for deskew in (True, False):
        ref = build_reference(scans, m, cfg.laser_offset, initial_pose=rec.initial_pose, deskew=deskew)
        truth = interpolate_poses(ref.t, rec.truth_t, rec.truth_poses)
        g = ref.good & np.all(np.isfinite(truth), axis=1)
        assert g.sum() > 0.9 * len(scans)
        err = np.hypot(*(ref.poses[g, :2] - truth[g, :2]).T)
        medians[deskew] = np.median(err)
        if deskew:
            assert np.median(err) < 0.005 and np.percentile(err, 95) < 0.015, (np.median(err), np.percentile(err, 95))
    assert medians[False] > 3 * medians[True], medians


# ------------------------------------------------------------------ along / cross track


def test_along_cross_decomposition_and_lag():
    t = np.arange(0.0, 10.0, 0.025)
    # reference: along +y at 2 m/s, heading +y; the estimate 0.05 s late and 0.03 m to the right
    ref = np.stack([np.zeros_like(t), 2.0 * t, np.full_like(t, math.pi / 2)], 1)
    est = np.stack([np.full_like(t, 0.03), 2.0 * (t - 0.05), np.full_like(t, math.pi / 2 + 0.01)], 1)
    e = track_errors(t, est, t, ref)
    assert np.allclose(e.along[2:-2], -0.1)  # behind by v * lag
    assert np.allclose(e.cross[2:-2], -0.03)  # +x is to the right of a car heading +y
    assert np.allclose(e.position[2:-2], math.hypot(0.1, 0.03))
    assert np.allclose(e.heading, 0.01)
    assert lag_from_along(e) == pytest.approx(0.05, abs=1e-3)
    assert best_lag(t, est, t, ref) == pytest.approx(0.05, abs=0.0025)
    # driving backwards: along-track follows the direction of travel, not the heading
    back = ref.copy()
    back[:, 1] = -2.0 * t
    est_b = est.copy()
    est_b[:, 1] = -2.0 * (t - 0.05)
    eb = track_errors(t, est_b, t, back)
    assert np.allclose(eb.along[2:-2], -0.1) and np.allclose(eb.cross[2:-2], 0.03)


def test_dead_reckon_matches_integrate_twist():
    from localization.core.geometry import integrate_twist
    t = np.array([0.0, 0.02, 0.04, 0.06])
    tw = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [2.0, 0.1, -0.3], [1.5, 0.0, 0.2]])
    p = dead_reckon(t, tw, [0.04, 0.05])
    expect = compose(integrate_twist(*tw[1], 0.02), integrate_twist(*tw[2], 0.02))
    np.testing.assert_allclose(p[0], expect, atol=1e-12)
    np.testing.assert_allclose(p[1], compose(expect, integrate_twist(*tw[3], 0.01)), atol=1e-12)


# ------------------------------------------------------------------ replay


def test_replay_scores_against_the_reference(tmp_path):
    from localization.tools.replay import main
    bag = sim_bag("trial1_noise0", duration=6.0)
    out = tmp_path / "out"
    assert main([str(bag), "--map", "stata_basement", "--out", str(out), "--reference", "--quiet",
                 "--particles", "500", "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    for key in ("reference_error_m", "along_track_error_m", "cross_track_error_m", "heading_error_ref_deg",
                "best_lag_s", "reference_scans", "reference_ambiguous", "truth_along_track_error_m"):
        assert key in m, key
    assert m["reference_scans"] > 200 and m["reference_scored"] > 0.8 * m["reference_scans"]
    assert m["reference_vs_truth_m"]["median"] < 0.02
    # against truth and against the reference the estimate's error agrees to the reference's accuracy
    assert abs(m["reference_error_m"]["median"] - m["ct_error_m"]["median"]) < 0.02
    assert (out / "reference.png").is_file()


def test_real_bag_replay_reference_figures(tmp_path):
    """localization-replay on a real bag (no truth): the estimate scored against the reference.
    Bounds catch a regression (docs/replay.md has the measured figures)."""
    from localization.core.paths import config_dir
    from localization.tools.replay import main
    rb = REAL_BAGS["bag3"]
    out = tmp_path / "out"
    assert main([str(real_bag_path("bag3")), "--map", rb.map, "--params", str(config_dir() / "real_params.yaml"),
                 "--initial-pose", ",".join(map(str, rb.start)), "--out", str(out), "--quiet", "--no-plots",
                 "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["reference_good"] >= 0.9 * m["reference_scans"]
    assert m["reference_error_m"]["median"] <= 0.08, m["reference_error_m"]
    assert m["reference_error_m"]["p95"] <= 0.30, m["reference_error_m"]
    assert abs(m["along_track_error_m"]["mean"]) <= 0.08, m["along_track_error_m"]
    assert m["abs_cross_track_error_m"]["median"] <= 0.05, m["abs_cross_track_error_m"]
