"""The correlative scan matcher and the reference track: kernels equal
their numpy references, branch and bound equals the exhaustive search (also at the map's edges), the reference track
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
from localization.eval.datasets import REAL_BAGS, read_scans, real_bag, real_bag_path, sim_bag, trial_config
from localization.eval.metrics import interpolate_poses
from localization.eval.reference import (
    FIT_NORMAL_PERCENTILE,
    FIT_SHARE,
    OdometryNoise,
    best_lag,
    better_fit_elsewhere,
    build_reference,
    constrained_axes,
    dead_reckon,
    lag_from_along,
    match_information,
    odometry_chain,
    odometry_chain_loop,
    odometry_consistency,
    pose_fit,
    read_odometry,
    scan_beams,
    track_errors,
)
from localization.sim import simulate

# ------------------------------------------------------------------ kernels


@pytest.mark.parametrize("low, high", [(-5, 95), (8, 82)], ids=["partly-off-the-grid", "inside"])
def test_score_kernel_equals_numpy_reference_bit_for_bit(low, high):
    """Candidates with endpoints off the grid (tested beam by beam) and wholly inside it (summed without
    the test): the same bits as the reference's running sum."""
    rng = np.random.default_rng(0)
    grid = rng.random((80, 90)).astype(np.float32)
    cols = rng.integers(low, high, (7, 300)).astype(np.int64)
    rows = rng.integers(low, high - 10, (7, 300)).astype(np.int64)
    cj = rng.integers(0, 7, 500).astype(np.int64)
    cu = rng.integers(-12, 13, 500).astype(np.int64)  # "inside": some shifts take the endpoints just past the edges
    cv = rng.integers(-12, 13, 500).astype(np.int64)
    fast = K.score_candidates(grid, cols, rows, cj, cu, cv)
    ref = K.score_candidates_numpy(grid, cols, rows, cj, cu, cv)
    assert np.array_equal(fast, ref)


def test_sdf_kernel_equals_numpy_reference_bit_for_bit():
    """The Gauss–Newton finish's bilinear signed distance and its gradient, compiled and in numpy: the same
    values, for endpoints inside, on the edges of and off the grid, and a non-finite one (numpy's path)."""
    rng = np.random.default_rng(3)
    sdf = (rng.normal(size=(60, 70)) * 5).astype(np.float32)
    for k in range(20):
        g = np.array([rng.uniform(-5, 75), rng.uniform(-5, 65), rng.uniform(-4, 4)])
        qg = rng.normal(size=(200, 2)) * rng.uniform(1, 40)
        fast, ref = K.sdf_at(sdf, g, qg), K.sdf_at_numpy(sdf, g, qg)
        for a, b in zip(fast, ref):
            assert a.dtype == b.dtype == np.float64
            assert np.array_equal(a, b)
    for a, b in zip(K.sdf_at(sdf, g, qg.astype(np.float32)), K.sdf_at_numpy(sdf, g, qg.astype(np.float32))):
        assert np.array_equal(a, b)  # float32 endpoints: numpy's own arithmetic
    qg[5] = np.inf
    with np.errstate(invalid="ignore"):  # numpy's own warnings on the inf endpoint
        for a, b in zip(K.sdf_at(sdf, g, qg), K.sdf_at_numpy(sdf, g, qg)):
            assert np.array_equal(a, b, equal_nan=True)


def test_max_pool_bounds_every_cell_of_its_block():
    """P[v + k-1, u + k-1] = max of the block from (u, v), also for blocks hanging over either edge."""
    rng = np.random.default_rng(1)
    g = rng.random((23, 31))
    k = 4
    P = max_pool(g, k)
    assert P.shape == (23 + k - 1, 31 + k - 1)
    for r in range(-(k - 1), 23):
        for c in range(-(k - 1), 31):
            assert P[r + k - 1, c + k - 1] == g[max(r, 0):r + k, max(c, 0):c + k].max(), (r, c)


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
    bounds = matcher.coarse_bounds(cols, rows, jj, uu, vv)
    order = np.argsort(-bounds, kind="stable")
    args = (matcher.L, cols, rows, jj[order], uu[order], vv[order], bounds[order], k, W)
    fast = K.branch_and_bound(*args)
    ref = K.branch_and_bound_numpy(*args)
    assert fast == ref  # the same score, bit for bit, at the same shift
    # the coarse bounds really bound: every block's bound >= the best fine score inside it
    assert bounds.max() >= fast[0]


def test_branch_and_bound_equals_its_reference_bit_for_bit_over_the_grids_edges():
    """Every block expanded (no bound prunes) on a dense random grid, the endpoints near its edges so that
    shifted patches lie inside, straddle an edge or leave the grid: the same score bits at the same shift."""
    rng = np.random.default_rng(5)
    grid = rng.random((60, 70)).astype(np.float32)
    k, W = 4, 8
    cols = rng.integers(3, 67, (5, 200)).astype(np.int64)
    rows = rng.integers(3, 57, (5, 200)).astype(np.int64)
    cols[1] = rng.integers(9, 61, 200)  # one rotation whose patches stay inside for the small shifts
    rows[1] = rng.integers(9, 51, 200)
    starts = np.arange(-W, W + 1, k)
    jj, uu, vv = (a.ravel().astype(np.int64) for a in np.meshgrid(np.arange(5), starts, starts, indexing="ij"))
    order = rng.permutation(len(jj))
    args = (grid, cols, rows, jj[order], uu[order], vv[order], np.full(len(jj), 2.0), k, W)
    assert K.branch_and_bound(*args) == K.branch_and_bound_numpy(*args)
    acc = np.empty((k, k))
    for j, du0, dv0 in zip(jj, uu, vv):  # every block's every total, not only the best
        nu, nv = min(du0 + k, W + 1) - du0, min(dv0 + k, W + 1) - dv0
        K._score_block(grid, cols, rows, j, du0, nu, dv0, nv, acc)
        DU, DV = np.meshgrid(np.arange(du0, du0 + nu), np.arange(dv0, dv0 + nv), indexing="ij")
        ref = K.score_candidates_numpy(grid, cols, rows, np.full(DU.size, j), DU.ravel(), DV.ravel())
        assert np.array_equal(acc[:nv, :nu].T.ravel() / cols.shape[1], ref), (j, du0, dv0)


def _exhaustive(matcher, cols, rows, W):
    """Every rotation and whole-cell shift in the window scored on the fine grid: (best, j, du, dv)."""
    J, du, dv = np.meshgrid(np.arange(cols.shape[0]), np.arange(-W, W + 1), np.arange(-W, W + 1), indexing="ij")
    J, du, dv = (a.ravel().astype(np.int64) for a in (J, du, dv))
    s = K.score_candidates_numpy(matcher.L, cols, rows, J, du, dv)
    i = int(np.argmax(s))
    return float(s[i]), int(J[i]), int(du[i]), int(dv[i])


def _walled_room() -> OccupancyMap:
    """A 6 m square room (0.05 m cells) whose walls are the grid's outermost rows and columns, a box inside."""
    data = np.zeros((120, 120), dtype=np.int8)
    data[0, :] = data[-1, :] = data[:, 0] = data[:, -1] = 100
    data[70:80, 60:75] = 100
    return OccupancyMap(data, 0.05, (0.0, 0.0, 0.0))


@pytest.mark.parametrize("truth, offset", [
    ((0.45, 0.45, -3 * math.pi / 4), (0.25, 0.25, 0.0)),  # facing the grid's low corner: walls on row 0 / col 0
    ((0.50, 3.0, math.pi), (0.25, 0.0, 0.02)),  # facing the low x edge
    ((3.0, 0.50, -math.pi / 2), (0.0, 0.3, -0.02)),  # facing the low y edge
    ((5.55, 5.55, math.pi / 4), (-0.25, -0.25, 0.0)),  # the high corner
])
def test_search_equals_exhaustive_search_at_the_map_edges(truth, offset):
    """Branch and bound finds the exhaustive search's best also when the best pose's coarse block
    hangs over the grid's low edge (its endpoints partly off the grid, partly on the wall there)."""
    m = _walled_room()
    matcher = CorrelativeMatcher(m)
    angles = np.linspace(-0.75 * np.pi, 0.75 * np.pi, 1081)
    mount = (0.275, 0.0, 0.0)
    truth = np.asarray(truth)
    ranges = ExactRayCaster(m, 10.0).cast(compose(truth, mount)[None], angles)[0]
    q = np.stack([0.275 + ranges * np.cos(angles), ranges * np.sin(angles)], 1) / m.resolution
    W = 8
    g0 = m.world_to_grid_pose(truth + np.asarray(offset))
    phis = g0[2] + np.arange(-5, 6) * matcher.angle_step_for(q)
    best, j, du, dv, cols, rows = matcher.search(q, g0, phis, W)
    ref = _exhaustive(matcher, cols, rows, W)
    assert best == pytest.approx(ref[0], abs=1e-12)
    assert (j, du, dv) == ref[1:]
    assert best > 0.9  # the true pose is in the window and found
    r = matcher.match(ranges, angles, mount, truth + np.asarray(offset))
    assert np.hypot(*(r.pose[:2] - truth[:2])) < 0.02, r.pose


def test_rotation_step_moves_the_farthest_endpoint_at_most_one_cell():
    m = _walled_room()
    matcher = CorrelativeMatcher(m)
    rng = np.random.default_rng(3)
    for far in (1.0, 8.0, 30.0):  # metres to the farthest endpoint
        q = rng.uniform(-1.0, 1.0, (500, 2))
        q[0] = (far, 0.0)
        qg = q / m.resolution
        step = matcher.angle_step_for(qg)
        assert step <= MatcherConfig().max_angle_step
        cells = np.hypot(*qg.T).max() * step  # arc of the farthest endpoint per step, cells
        assert cells <= 1.0 + 1e-12
        if far > 2.5:  # not capped: exactly one cell
            assert cells == pytest.approx(1.0)
    assert CorrelativeMatcher(m, MatcherConfig(angle_step=0.006)).angle_step_for(qg) == 0.006  # a fixed step


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


def _odometry(rec):
    return rec.odometry.t, rec.odometry.twist


def test_reference_track_follows_ground_truth(trial1):
    """Seeded by the start pose (0.5 m off) and the odometry only: every scan matched, every axis
    constrained, the smoothed track on the simulator's truth to the millimetre, and its own σ says so."""
    cfg, m, rec = trial1
    ref = build_reference(_scans(cfg, rec), m, cfg.laser_offset, _odometry(rec), initial_pose=rec.initial_pose)
    truth = interpolate_poses(ref.t, rec.truth_t, rec.truth_poses)
    good = ref.good & np.all(np.isfinite(truth), axis=1)
    assert good.mean() > 0.9, ref.counts
    err = np.hypot(*(ref.poses[good, :2] - truth[good, :2]).T)
    assert np.median(err) < 0.005, np.median(err)
    assert np.percentile(err, 95) < 0.01
    s = ref.summary()
    assert s["matched_share"] > 0.95 and min(s["constrained_share"].values()) > 0.9, s
    assert s["std_along_m"]["median"] < 0.01 and s["std_cross_m"]["median"] < 0.01
    assert abs(ref.odometry["speed_scale"] - 1.0) < 0.01 and abs(ref.odometry["time_offset_s"]) < 0.01


def test_reference_track_recovers_the_odometry_timing_and_speed_scale():
    """The calibration trial: odometry 30 ms late, speed 5 % short; the smoothing's unknowns."""
    cfg = trial_config("calibration", duration=20.0)
    m = load_map(cfg.map)
    rec = simulate(cfg, m)
    ref = build_reference(_scans(cfg, rec), m, cfg.laser_offset, _odometry(rec), initial_pose=rec.initial_pose,
                          range_scale=1.0 / cfg.range_scale)
    assert ref.odometry["time_offset_s"] == pytest.approx(-cfg.odom_latency, abs=0.008), ref.odometry
    assert ref.odometry["speed_scale"] == pytest.approx(1.0 / cfg.speed_scale, rel=0.005), ref.odometry
    truth = interpolate_poses(ref.t, rec.truth_t, rec.truth_poses)
    g = ref.good & np.all(np.isfinite(truth), axis=1)
    assert g.mean() > 0.9
    assert np.median(np.hypot(*(ref.poses[g, :2] - truth[g, :2]).T)) < 0.01


def test_reference_track_deskews_a_fast_sweeping_scan():
    """The fast trial (up to 7 m/s, 18.75 ms sweep: the scan smeared over 0.13 m): deskewed, the
    reference stays at the millimetre level; rigid, it does not."""
    cfg = trial_config("fast", duration=5.0)
    m = load_map(cfg.map)
    rec = simulate(cfg, m)
    assert rec.scan_time_increment > 0
    scans = _scans(cfg, rec)
    medians = {}
    for deskew in (True, False):
        ref = build_reference(scans, m, cfg.laser_offset, _odometry(rec), initial_pose=rec.initial_pose,
                              deskew=deskew)
        truth = interpolate_poses(ref.t, rec.truth_t, rec.truth_poses)
        g = ref.usable & np.all(np.isfinite(truth), axis=1)
        assert g.sum() > 0.9 * len(scans)
        err = np.hypot(*(ref.matched[g, :2] - truth[g, :2]).T)
        medians[deskew] = np.median(err)
        if deskew:
            assert np.median(err) < 0.003 and np.percentile(err, 95) < 0.01, (np.median(err), np.percentile(err, 95))
    assert medians[False] > 3 * medians[True], medians


def _corridor_scan(junction: bool):
    m = _corridor(1200, junction)  # 60 m long: the 10 m lidar sees neither end
    angles = np.linspace(-0.75 * np.pi, 0.75 * np.pi, 1081)
    truth = np.array([30.0, 2.0, 0.0])
    ranges = ExactRayCaster(m, 10.0).cast(compose(truth, (0.275, 0.0, 0.0))[None], angles)[0]
    return m, np.where(ranges >= 10.0, np.inf, ranges), angles, truth


@pytest.mark.parametrize("junction", [False, True])
def test_match_information_leaves_a_corridor_free_along_it(junction):
    """Λ from the beams on the walls: across the corridor and in heading pinned either way; along it
    free without the side opening (σ of metres), pinned with it."""
    m, ranges, angles, truth = _corridor_scan(junction)
    info = match_information(m, ranges, angles, (0.275, 0.0, 0.0), truth, angles[1] - angles[0])
    cov = info.covariance
    along, cross = constrained_axes(info.information, info.median_range, m.resolution, np.array([1.0, 0.0]))[3:]
    assert cross and math.sqrt(cov[1, 1]) < 0.01
    assert along == junction, (math.sqrt(cov[0, 0]), info.segments)
    if not junction:
        assert math.sqrt(cov[0, 0]) > 1.0


def test_odometry_chain_equals_its_loop_reference():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.01, 0.03, 400))
    tw = rng.normal(size=(400, 3)) * [2.0, 0.1, 1.0]
    np.testing.assert_allclose(odometry_chain(t, tw, 1.05, 0.9, 0.02), odometry_chain_loop(t, tw, 1.05, 0.9, 0.02),
                               atol=1e-9)


@pytest.mark.parametrize("block", [None, 1])
def test_offset_profile_equals_its_loop_reference(monkeypatch, block):
    """The time-offset profile, every offset × scan dead-reckoned in blocks, equals the one-offset-at-a-time
    loop bit for bit (also with one offset per block)."""
    from localization.eval.reference import smoother
    rng = np.random.default_rng(7)
    odo_t = np.cumsum(rng.uniform(0.015, 0.025, 500))
    tw = np.column_stack([2.0 + 0.3 * rng.normal(size=500), 0.02 * rng.normal(size=500), rng.normal(size=500)])
    t = np.arange(odo_t[20], odo_t[-20], 0.025)
    K = len(t)
    X = compose(dead_reckon(odo_t, tw, t - 0.05, 1.04), rng.normal(size=(K, 3)) * [0.005, 0.005, 0.002])
    use = np.zeros(K, dtype=bool)
    use[::3] = True
    info = np.broadcast_to(np.eye(3) * 1e4, (K, 3, 3)).copy()
    scales = {"match": 1.0, "odo_x": 1.0, "odo_y": 1.0, "odo_theta": 1.0}
    graph = smoother._Graph(t, X, info, use, (odo_t, tw), OdometryNoise(), scales)
    graph.set_sigmas(np.array([1.0]))
    if block is not None:
        monkeypatch.setattr(smoother, "PROFILE_BLOCK", block)
    grid = np.arange(-0.3, 0.3 + 1e-9, 0.002)
    cost, scale = graph.offset_profile(X, grid)
    ref_cost, ref_scale = graph.offset_profile_loop(X, grid)
    np.testing.assert_array_equal(cost, ref_cost)
    np.testing.assert_array_equal(scale, ref_scale)
    assert abs(grid[np.argmin(cost)] - 0.05) < 0.02 and abs(scale[np.argmin(cost)] - 1.04) < 0.02


def test_marginal_covariances_equal_the_dense_inverse():
    """The blocks of (JᵀJ)⁻¹ from the block-tridiagonal recursion and the Schur complement equal a dense
    inverse (a small pose graph: consecutive factors, some matches, one unknown on every odometry row)."""
    from scipy.sparse import csr_matrix

    from localization.eval.reference import _marginal_covariances, block_tridiagonal_inverse
    rng = np.random.default_rng(5)
    K = 40
    rows = []
    for j in range(K - 1):
        for _ in range(3):
            r = np.zeros(3 * K + 1)
            r[3 * j:3 * j + 6] = rng.normal(size=6)
            r[-1] = rng.normal()
            rows.append(r)
    for k in range(0, K, 3):
        for _ in range(3):
            r = np.zeros(3 * K + 1)
            r[3 * k:3 * k + 3] = rng.normal(size=3) * 5
            rows.append(r)
    r = np.zeros(3 * K + 1)
    r[-1] = 2.0
    rows.append(r)
    J = np.array(rows)
    cov, nxt, pcov = _marginal_covariances(csr_matrix(J), K)
    full = np.linalg.inv(J.T @ J + 1e-12 * np.eye(3 * K + 1))
    for k in range(K):
        np.testing.assert_allclose(cov[k], full[3 * k:3 * k + 3, 3 * k:3 * k + 3], rtol=1e-8, atol=1e-12)
    for k in range(K - 1):
        np.testing.assert_allclose(nxt[k], full[3 * k:3 * k + 3, 3 * k + 3:3 * k + 6], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(pcov, full[-1:, -1:], rtol=1e-8)
    A = rng.normal(size=(12, 12))
    A = A @ A.T + 12 * np.eye(12)
    A[np.abs(np.subtract.outer(np.arange(12) // 3, np.arange(12) // 3)) > 1] = 0.0  # block-tridiagonal
    d, u = block_tridiagonal_inverse(np.array([A[3 * k:3 * k + 3, 3 * k:3 * k + 3] for k in range(4)]),
                                     np.array([A[3 * k:3 * k + 3, 3 * k + 3:3 * k + 6] for k in range(3)]))
    inv = np.linalg.inv(A)
    np.testing.assert_allclose(d[2], inv[6:9, 6:9], atol=1e-12)
    np.testing.assert_allclose(u[1], inv[3:6, 6:9], atol=1e-12)


def test_real_pioneer_bag_global_start_finds_the_given_start():
    """trace0 (a Pioneer: 726 beams, 5.6 m) matched from a global search lands where the given start
    pose says, and agrees with the track started there."""
    rb = real_bag("trace0")
    m = load_map(rb.map)
    path = real_bag_path("trace0")
    scans = read_scans(path, rb.scan_topic)[:150]
    odo = read_odometry(path, rb.odom_topic)
    tracks = [build_reference(scans, m, (0.135, 0.0, 0.0), odo, start, scan_stamp="last_beam")
              for start in (rb.start, None)]
    assert tracks[1].counts["start"].startswith("global")
    for ref in tracks:
        assert ref.summary()["matched_share"] > 0.8, ref.counts
    d = np.hypot(*(tracks[0].poses[:, :2] - tracks[1].poses[:, :2]).T)
    assert np.median(d) < 0.02 and np.hypot(*(tracks[0].poses[0, :2] - rb.start[:2])) < 0.5


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


def test_pose_fit_scores_only_poses_where_the_scan_fits_the_map(trial1):
    """The yardstick's fit check: at its smoothed poses the simulated scans fit the map (nothing left out
    as poor fit); moved 0.4 m and 0.3 rad the same scans do not, and such poses would not be scored."""
    cfg, m, rec = trial1
    scans = _scans(cfg, rec)
    ref = build_reference(scans, m, cfg.laser_offset, _odometry(rec), initial_pose=rec.initial_pose)
    assert ref.fit is not None and np.nanmedian(ref.fit) > 0.9 and ref.counts["poor_fit"] == 0
    assert ref.summary()["poor_fit_share"] == 0.0
    beams = scan_beams(scans, False)
    moved = compose(ref.poses, np.array([0.4, 0.4, 0.3]))
    off = pose_fit(m, beams, moved, cfg.laser_offset)
    assert np.nanmedian(off) < FIT_SHARE * np.percentile(ref.fit[ref.accepted], FIT_NORMAL_PERCENTILE)
    assert np.isnan(pose_fit(m, beams[:1], np.full((1, 3), np.nan), cfg.laser_offset)[0])


def test_odometry_consistency_flags_a_track_that_stops_following_the_odometry():
    """1 m/s straight for 20 s by the odometry; a track that stalls for 4 s (wrong matches holding it) is
    inconsistent around the stall; a track that slides on while the odometry reads 0 (wheels locked) is a skid."""
    t = np.arange(0.0, 20.0, 0.1)
    odo = (t.copy(), np.column_stack([np.ones_like(t), np.zeros_like(t), np.zeros_like(t)]))
    x = t.copy()
    track = np.column_stack([x, np.zeros_like(t), np.zeros_like(t)])
    noise = OdometryNoise()
    ok, skid = odometry_consistency(t, track, odo, 1.0, 0.0, noise, 0.05)
    assert ok.all() and not skid.any()
    stalled = track.copy()
    stalled[:, 0] = np.where(t < 8.0, t, np.where(t < 12.0, 8.0, t - 4.0))  # stands still 8-12 s, then 4 m behind
    ok, skid = odometry_consistency(t, stalled, odo, 1.0, 0.0, noise, 0.05)
    assert not ok[(t > 8.5) & (t < 11.5)].any() and ok[t < 3.0].all() and not skid.any()
    locked = (t.copy(), np.column_stack([np.where(t < 16.0, 1.0, 0.0), np.zeros_like(t), np.zeros_like(t)]))
    ok, skid = odometry_consistency(t, track, locked, 1.0, 0.0, noise, 0.05)  # the track slides on past 16 s
    assert not ok[t > 17.0].all() and skid[t > 17.0].all() and ok[t < 10.0].all()
    slow = (t.copy(), np.column_stack([np.full_like(t, 0.5), np.zeros_like(t), np.zeros_like(t)]))
    ok, skid = odometry_consistency(t, track, slow, 1.0, 0.0, noise, 0.05)  # outruns wheels that keep rolling:
    assert not ok[(t > 4.0) & (t < 16.0)].any() and not skid.any()  # carried off by matches, not a skid


def test_a_track_is_not_scored_where_the_map_fits_the_scan_clearly_better_nearby(trial1):
    """The yardstick's own poses: no better place nearby. A track carried 1.2 m and 0.15 rad off for 2 s
    (where a changed room let the odometry and look-alike matches take it): those half seconds are found
    by the wide search, the rest is not touched."""
    cfg, m, rec = trial1
    scans = _scans(cfg, rec)
    ref = build_reference(scans, m, cfg.laser_offset, _odometry(rec), initial_pose=rec.initial_pose)
    assert ref.counts["better_fit_elsewhere"] == 0 and ref.summary()["better_fit_elsewhere_share"] == 0.0
    beams = scan_beams(scans, False)
    off = (ref.t - ref.t[0] > 2.0) & (ref.t - ref.t[0] < 4.0)
    carried = ref.poses.copy()
    carried[off] = compose(carried[off], np.array([0.9, 0.8, 0.15]))
    fit = pose_fit(m, beams, carried, cfg.laser_offset)
    flagged = better_fit_elsewhere(m, beams, ref.t, carried, fit, cfg.laser_offset)
    rel = ref.t - ref.t[0]
    assert flagged[(rel > 2.5) & (rel < 3.5)].all()  # every half second inside the carried stretch
    assert not flagged[(rel < 1.5) | (rel > 4.5)].any()  # and nothing away from it
    assert not better_fit_elsewhere(m, beams, ref.t, np.full_like(carried, np.nan), fit, cfg.laser_offset).any()
