"""Filter health, global localization, kidnapped-robot recovery and the stationary car."""
import logging
import math

import numpy as np
import pytest
from helpers import corridor_map, wrap_sensor_updates

from localization.benchmarks import robustness as RB
from localization.core.filter.mcl import Estimate, MonteCarloLocalizer, SensorUpdateResult, Snapshot
from localization.core.localizer import Localizer
from localization.core.localizer.health import AgreementScorer, HealthMonitor, cloud_spread, cloud_spread_numpy
from localization.core.localizer.recovery import Action, Decision, SwitchGlide, is_jump
from localization.core.localizer.timeline import PoseEstimate
from localization.core.models.beam import BeamModel as SensorModel
from localization.core.models.motion import MotionModel
from localization.core.occupancy_map import load_map
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData
from localization.eval.datasets import trial_config
from localization.eval.feed import Feeder
from localization.sim import simulate

ANGLES = np.linspace(-2.356, 2.356, 1081)
INC = ANGLES[1] - ANGLES[0]


@pytest.fixture(scope="module")
def stata():
    return load_map("stata_basement")


def params(**kw):
    values = dict(ray_caster="lookup_table", random_seed=4)
    values.update(kw)
    return Parameters(values)


# ------------------------------------------------------------------------------- HealthMonitor
def test_monitor_is_lost_only_after_a_sustained_drop():
    m = HealthMonitor(fast_alpha=0.2, slow_alpha=0.02, lost_floor=0.2, lost_ratio=0.5, lost_updates=10)
    assert math.isnan(m.health)
    rng = np.random.default_rng(0)
    for _ in range(300):  # normal driving: noisy but good agreement, occasional bad scans
        a = 0.15 if rng.random() < 0.05 else rng.uniform(0.75, 0.98)
        assert not m.update(a)
    assert 0.7 < m.health <= 1.0 and 0.7 < m.slow <= 1.0
    assert not m.update(math.nan)  # a scan without valid beams says nothing
    lost = []
    while not (lost and lost[-1]) and len(lost) < 30:
        lost.append(m.update(0.1))
    assert 10 <= len(lost) <= 16  # the fast average falls within a few updates, then 10 low ones in a row
    m.reset(keep_slow=True)  # re-initialised (recovery): the long-term average is kept ...
    assert math.isnan(m.health) and m.low_count == 0 and m.slow > 0.65
    lost = [m.update(0.22) for _ in range(10)]  # ... so a cloud re-converged to a wrong place is judged by it
    assert lost[-1]
    m.reset()
    assert math.isnan(m.slow)
    assert not any(m.update(0.22) for _ in range(30))  # above the floor (0.2), no history: not lost


def test_monitor_from_parameters():
    m = HealthMonitor.from_params(Parameters(health_lost_updates=7, health_lost_floor=0.2))
    assert m.lost_updates == 7 and m.lost_floor == 0.2


def test_cloud_spread():
    assert cloud_spread(np.diag([4.0, 1.0, 0.1])) == pytest.approx(2.0)
    assert cloud_spread(np.full((3, 3), np.nan)) == math.inf
    assert cloud_spread(np.array([[1.0, 0.0], [0.0, np.inf]])) == math.inf
    assert cloud_spread(np.zeros((3, 3))) == 0.0


def test_cloud_spread_equals_its_numpy_reference():
    rng = np.random.default_rng(3)
    for _ in range(2000):
        a = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-4.0, 1.0)
        cov = a @ a.T
        cov[0, 1] += rng.normal() * 1e-9 * cov[0, 0]  # not quite symmetric, as a summed covariance can be
        assert cloud_spread(cov) == pytest.approx(cloud_spread_numpy(cov), rel=1e-12, abs=1e-15)
    degenerate = np.array([[1e-30, 0.0, 0.0], [0.0, -1e-30, 0.0], [0.0, 0.0, 1.0]])  # rounding below zero
    assert cloud_spread(degenerate) == pytest.approx(cloud_spread_numpy(degenerate), abs=1e-15)


# ------------------------------------------------------------------------------- agreement
def test_health_high_at_the_true_pose_and_low_when_wrong(stata):
    true = np.array([-6.6, 20.5, -2.24])
    laser = true + [0.275 * math.cos(true[2]), 0.275 * math.sin(true[2]), 0.0]
    ranges = ExactRayCaster(stata, 10.0).cast(laser[None], ANGLES)[0]
    scorer = AgreementScorer(stata, (0.275, 0.0, 0.0))
    good = scorer.score(true, ranges, ANGLES, 0.02, 10.0)
    assert good > 0.9
    for off in ([1.0, 0.0, 0.0], [0.0, 0.0, 0.5], [8.0, -3.0, 1.0]):
        assert scorer.score(true + off, ranges, ANGLES, 0.02, 10.0) < 0.5
    assert math.isnan(scorer.score(true, np.full(1081, np.nan), ANGLES, 0.02, 10.0))


# ------------------------------------------------------------------------------- resize
def test_resize_keeps_the_distribution():
    rng = np.random.default_rng(1)
    f = MonteCarloLocalizer(MotionModel(rng=rng), SensorModel(), 20000, rng=rng)
    f.initialize_gaussian([1.0, 2.0, 0.3], std=(0.5, 0.2, 0.1))
    f.resize(2000)
    assert f.particles.shape == (2000, 3) and f.num_particles == 2000 and np.isclose(f.weights.sum(), 1.0)
    est = f.estimate()
    assert np.allclose(est.pose, [1.0, 2.0, 0.3], atol=0.05)
    assert np.allclose(np.sqrt(np.diag(est.covariance)), [0.5, 0.2, 0.1], rtol=0.15)
    with pytest.raises(ValueError):
        f.resize(0)


# ------------------------------------------------------------------------------- simulated runs
def test_normal_short_trial_keeps_health_high_without_recovery(stata):
    rec = simulate(trial_config("trial3_noise0.6", duration=10.0), stata)
    loc = Localizer(params(), logging.getLogger("test.normal"))
    loc.set_map(stata)
    run = RB.run_recording(rec, loc, init="pose")
    assert run.recoveries == 0 and loc.recoveries == 0
    assert run.health.size > 100 and np.median(run.health) > 0.85 and run.health.min() > 0.5
    cmp = RB.ct_errors(rec, run)
    assert cmp.ct_error[cmp.t > 2.0].max() < 0.3


def test_kidnapped_robot_recovers(stata, caplog):
    kidnap_at = 4.0
    cfg = RB.loop_config(400, kidnap_at + 12.0, seed=11, kidnap_at=kidnap_at, kidnap_to=RB.loop_pose(1700))
    rec = simulate(cfg, stata)
    step = rec.trajectory.kidnapped_at_step
    assert np.hypot(*(rec.trajectory.poses[step, :2] - rec.trajectory.poses[step - 1, :2])) > 10.0
    loc = Localizer(params(), logging.getLogger("test.kidnap"))
    loc.set_map(stata)
    with caplog.at_level(logging.WARNING, logger="test.kidnap"):
        run = RB.run_recording(rec, loc, init="pose")
    assert run.recoveries >= 1 and "localization lost" in caplog.text
    cmp = RB.ct_errors(rec, run)
    assert cmp.ct_error[(cmp.t > 1.0) & (cmp.t < kidnap_at)].max() < 0.3  # tracking before
    back = RB.settle_time(cmp, kidnap_at)  # the search and confirmation, then the glide over the kidnap's 30+ m
    assert back is not None and back < RB.KIDNAP_WITHIN_S, back
    after = run.est_t > kidnap_at + 0.1  # the published pose never jumps, not even to where the robot was carried
    assert np.hypot(*np.diff(run.est_poses[after, :2], axis=0).T).max() < loc.params.recovery_switch_step + 0.1
    assert loc.num_particles == loc.params.num_particles  # shrunk back after converging
    assert run.health[-20:].min() > 0.7


def test_global_localization_converges_and_shrinks(stata):
    rec = simulate(RB.loop_config(1200, 8.0, seed=12), stata)
    loc = Localizer(params(global_num_particles=20000), logging.getLogger("test.global"))
    loc.set_map(stata)
    loc.initialize_global(0.0)
    assert loc.num_particles == 20000 and loc.global_mode and math.isnan(loc.health)
    run = RB.run_recording(rec, loc, init="none")
    cmp = RB.ct_errors(rec, run)
    t = RB.settle_time(cmp, 0.0)
    assert t is not None and t < 8.0
    assert not loc.global_mode and loc.num_particles == loc.params.num_particles


def test_recovery_can_be_switched_off(stata):
    kidnap_at = 3.0
    cfg = RB.loop_config(400, kidnap_at + 4.0, seed=11, kidnap_at=kidnap_at, kidnap_to=RB.loop_pose(1700))
    rec = simulate(cfg, stata)
    loc = Localizer(params(recovery=False), logging.getLogger("test.norecovery"))
    loc.set_map(stata)
    run = RB.run_recording(rec, loc, init="pose")
    assert run.recoveries == 0  # lost, and it says so through health
    before = run.health[(run.health_t > 1.0) & (run.health_t < kidnap_at)]
    assert before.min() > 0.8 and run.health[-1] < 0.5 * before.mean()


# ------------------------------------------------------------------------------- stationary car
def test_stationary_car_does_not_drift_and_tightens_once():
    m = corridor_map()
    loc = Localizer(Parameters(num_particles=1000, random_seed=5, ray_caster="distance_transform"))
    loc.set_map(m)
    true = np.array([5.0, 1.5, 0.0])
    laser = true + [0.275, 0.0, 0.0]
    angles = np.linspace(-2.356, 2.356, 1081)
    ranges = ExactRayCaster(m, 10.0).cast(laser[None], angles)[0]
    loc.set_initial_pose(true + [0.1, 0.05, 0.05], np.diag([0.09, 0.09, 0.01]))
    spread0 = cloud_spread(loc.estimate.covariance)
    loc.on_odometry(TwistData(0.0, 0.0, 0.0, 0.0))
    first = loc.on_scan(ScanData(0.0, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 10.0)).estimate
    assert first is not None  # a sensor update runs right after /initialpose, standing still
    spread1 = cloud_spread(first.covariance)
    assert spread1 < spread0
    mean1 = first.pose.copy()
    particles1 = loc.particles()
    for k in range(1, 400):  # 8 s standing: zero twist at 50 Hz, scans in between
        loc.on_odometry(TwistData(0.02 * k, 0.0, 0.0, 0.0))
        scan = ScanData(0.02 * k + 0.01, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 10.0)
        assert loc.on_scan(scan).estimate is None
    assert np.array_equal(loc.particles(), particles1)  # no motion noise, no resampling jitter
    est = loc.estimate
    assert np.allclose(est.pose, mean1) and cloud_spread(est.covariance) <= spread1 + 1e-12


# ------------------------------------------------------------------------------- map disagrees: hold, never jump
def test_scans_the_map_cannot_explain_hold_the_pose_on_odometry_without_a_jump(caplog):
    """Clutter the map does not show (every beam a random range, scan after scan): the filter is judged
    lost, says the scans disagree with the map, keeps its pose on odometry, and no challenger wins
    (nowhere fits clearly and lastingly better): no jump between consecutive estimates."""
    m = corridor_map()
    loc = Localizer(Parameters(num_particles=500, random_seed=4, ray_caster="distance_transform",
                               health_lost_updates=5, recovery_search_period=0.5, recovery_particles=300),
                    logging.getLogger("test.hold"))
    loc.set_map(m)
    loc.set_initial_pose([3.0, 1.5, 0.0], np.diag([1e-4, 1e-4, 1e-4]))
    feeder = Feeder(loc)
    rng = np.random.default_rng(0)
    with caplog.at_level(logging.WARNING, logger="test.hold"):
        for k in range(400):  # 8 s at 0.25 m/s
            t = 0.02 * k
            feeder.odometry(TwistData(t, 0.25, 0.0, 0.0))
            if k % 2 == 1:
                feeder.scan(ScanData(t - 0.01, rng.uniform(0.3, 3.0, 181), -1.57, 1.57, 3.14 / 180, 0.02, 10.0))
    assert loc.status == "scans disagree with the map" and "localization lost" in caplog.text
    assert loc.recoveries == 0  # no switch
    t, poses = feeder.log.estimates()
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert steps.max() < 0.05  # never a jump: 0.25 m/s × 20 ms = 5 mm per message
    assert poses[-1, 0] == pytest.approx(3.0 + 0.25 * t[-1], abs=0.3)  # held on odometry
    assert poses[-1, 1] == pytest.approx(1.5, abs=0.3)


# ------------------------------------------------------------------------------- a switch glides
def test_a_switch_moves_the_published_pose_in_bounded_steps_to_the_new_place():
    glide = SwitchGlide(step=0.25, turn=0.2, farthest=2.0)
    published, target, cov = np.array([1.0, 2.0, 3.0]), np.array([1.6, 1.75, -3.0]), np.diag([1e-3, 1e-3, 1e-4])
    glide.start(published, target)
    assert glide.active
    path = [published]
    while glide.active and len(path) < 20:
        pose, c = glide.apply(path[-1], target, cov)
        if glide.active:  # still on its way: the covariance covers the distance still to go
            rest = target[:2] - pose[:2]
            assert c[0, 0] >= cov[0, 0] + 0.99 * rest[0] ** 2 and c[1, 1] >= cov[1, 1] + 0.99 * rest[1] ** 2
        else:
            assert np.array_equal(c, cov)
        path.append(pose)
    path = np.array(path)
    assert np.allclose(path[-1], target)  # there, exactly
    steps = np.hypot(*np.diff(path[:, :2], axis=0).T)
    turns = np.abs(np.angle(np.exp(1j * np.diff(path[:, 2]))))
    assert steps.max() <= 0.25 + 1e-12 and turns.max() <= 0.2 + 1e-12  # 0.65 m and 0.28 rad: 3 steps
    assert len(path) - 1 == 3
    assert turns.sum() == pytest.approx(2 * np.pi - 6.0)  # the short way round through ±π
    far = SwitchGlide(step=0.25, turn=0.2, farthest=2.0)
    far.start(published, published + [3.0, 0.0, 0.0])  # farther than farthest: published at once
    assert not far.active and np.array_equal(far.apply(published, target, cov)[0], target)
    unbounded = SwitchGlide(step=0.25, turn=0.2, farthest=0.0)  # the default: every switch glides
    unbounded.start(published, published + [30.0, 0.0, 0.0])
    assert unbounded.active
    off = SwitchGlide(step=0.0, turn=0.2, farthest=2.0)
    off.start(published, target)
    assert not off.active


START = np.array([-2.0, 0.0, 0.0])  # where the switch tests' Localizer is told it is


def _switch_published(stata, offset, switch_on: int, standing: bool, scans: int, **overrides):
    """A Localizer at START whose recovery decides a challenger won at START + ``offset`` on scan
    ``switch_on`` (1-based; the cloud moves there); its other scans update at the cloud's estimate (updates
    that leave the cloud as it is), or (``standing``) update nothing. The estimates the scans returned, the
    challenger's pose, the Localizer."""
    # the range scale is not learnt: it stays as configured
    loc = Localizer(params(num_particles=300, range_scale_estimation=False, **overrides),
                    logging.getLogger("test.glide"))
    loc.set_map(stata)
    loc.set_initial_pose(START, np.diag([1e-4, 1e-4, 1e-5]))
    there = START + offset
    challenger = Estimate(pose=there, covariance=np.diag([1e-4, 1e-4, 1e-5]))
    won = Snapshot(np.tile(there, (300, 1)), np.full(300, -np.log(300.0)))  # the challenger's particles
    wrap_sensor_updates(loc._pf, lambda real: lambda *a, **k: SensorUpdateResult(True, False, 300.0, 0.0))
    runs = []

    def decide(update):
        runs.append(update.time)
        if len(runs) == switch_on:
            return Decision(Action.SWITCH, challenger, glide=True, cloud=won)
        return Decision(Action.SKIP) if standing else Decision(Action.TRACK, update.estimate)

    loc._pipeline.recovery.decide = decide
    poses = []
    for k in range(scans):
        loc.on_odometry(TwistData(0.1 * k, 0.0, 0.0, 0.0))
        if not standing:
            loc.request_update()  # every scan reaches the decision
        est = loc.on_scan(ScanData(0.1 * k, np.ones(10), -1.0, 1.0, 0.2, 0.01, 10.0)).estimate
        if est is not None:
            poses.append(est.pose)
    return np.array(poses), there, loc


def test_a_near_switch_is_published_without_a_jump(stata):
    """A challenger wins 0.6 m from where the held cloud is: the published estimates reach it in steps
    of at most recovery_switch_step; the cloud itself is there at once."""
    poses, near, loc = _switch_published(stata, [0.5, 0.35, 0.1], switch_on=2, standing=False, scans=8)
    assert len(poses) == 8
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert steps.max() <= loc.params.recovery_switch_step + 1e-9 and steps.max() > 0.2  # in steps ...
    assert np.allclose(poses[-1], near)  # ... to the place the challenger won
    assert loc.recoveries == 1


def test_a_jump_is_judged_by_the_published_covariance_in_the_direction_of_the_move():
    """A cloud spread 0.4 m along x (a hold) and 3 cm along y: 1 m along x is within its spread, 1 m
    along y (or 0.3 m at 45°, outside 3σ there) is a jump; a round 0.5 m cloud owns a 1 m move."""
    elongated = PoseEstimate(stamp=0.0, pose=np.zeros(3), covariance=np.diag([0.4 ** 2, 0.03 ** 2, 0.01]))
    assert not is_jump(elongated, np.array([1.0, 0.0, 0.0]), 0.25)
    assert is_jump(elongated, np.array([0.0, 1.0, 0.0]), 0.25)
    assert is_jump(elongated, np.array([0.3, 0.3, 0.0]), 0.25)
    assert not is_jump(elongated, np.array([0.0, 0.2, 0.0]), 0.25)  # not farther than recovery_jump_glide
    assert not is_jump(elongated, np.array([0.0, 1.0, 0.0]), 0.0)  # the check off
    round_ = PoseEstimate(stamp=0.0, pose=np.zeros(3), covariance=np.diag([0.25, 0.25, 0.01]))
    assert not is_jump(round_, np.array([0.7, 0.7, 0.0]), 0.25)
    point = PoseEstimate(stamp=0.0, pose=np.zeros(3), covariance=np.zeros((3, 3)))
    assert is_jump(point, np.array([0.3, 0.0, 0.0]), 0.25)


@pytest.mark.parametrize("glide_max", [0.0, 2.0])
def test_a_far_switch_glides_on_with_every_scan_while_the_robot_stands(stata, glide_max):
    """A challenger wins 3.7 m away and the robot then stands still (no sensor update): by default the
    published estimates still reach the new place, one bounded step per scan; with
    recovery_switch_glide_max 2 m the switch is published at once."""
    poses, far, loc = _switch_published(stata, [3.0, 2.1, 0.3], switch_on=1, standing=True, scans=25,
                                        recovery_switch_glide_max=glide_max)
    assert np.allclose(poses[-1], far) and loc.recoveries == 1
    steps = np.hypot(*np.diff(np.vstack([START, poses])[:, :2], axis=0).T)
    if glide_max == 0.0:  # 3.66 m in steps of 0.25 m, with scans that update nothing
        assert steps.max() <= loc.params.recovery_switch_step + 1e-9 and len(poses) == 15
    else:  # farther than recovery_switch_glide_max: at once
        assert steps[0] == pytest.approx(math.hypot(3.0, 2.1)) and len(poses) == 1


def _tracking_jump(stata, start_cov, jump_glide=None):
    """A tracking Localizer whose cloud moves 0.6 m on its second scan without a switch (a cloud of two
    places whose weight moved): the published estimates of 8 scans and the cloud's place."""
    overrides = {} if jump_glide is None else {"recovery_jump_glide": jump_glide}
    # the range scale is not learnt: it stays as configured
    loc = Localizer(params(num_particles=300, range_scale_estimation=False, **overrides),
                    logging.getLogger("test.jump"))
    loc.set_map(stata)
    start = np.array([-2.0, 0.0, 0.0])
    loc.set_initial_pose(start, start_cov)
    there = start + [0.5, 0.35, 0.05]
    real_decide, runs = loc._pipeline.recovery.decide, []

    def decide(update):  # on its second scan the cloud is elsewhere
        runs.append(update.time)
        if len(runs) == 2:
            loc._pf.set_particles(np.tile(there, (300, 1)))
        if len(runs) >= 2:  # the move kept (this fake scan cannot score it), judged as the recovery does
            return Decision(Action.TRACK, Estimate(pose=there, covariance=np.diag([1e-4, 1e-4, 1e-5])),
                            glide=is_jump(update.published, there, loc.params.recovery_jump_glide))
        return real_decide(update)

    loc._pipeline.recovery.decide = decide
    poses = []
    for k in range(8):
        loc.on_odometry(TwistData(0.1 * k, 0.0, 0.0, 0.0))
        loc.request_update()  # every scan reaches the decision
        poses.append(loc.on_scan(ScanData(0.1 * k, np.ones(10), -1.0, 1.0, 0.2, 0.01, 10.0)).estimate.pose)
    return np.array(poses), there, loc


def test_a_tracking_cloud_that_moves_to_another_place_is_published_without_a_jump(stata):
    poses, there, loc = _tracking_jump(stata, np.diag([1e-4, 1e-4, 1e-5]))
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert steps.max() <= loc.params.recovery_jump_glide + 1e-9 and steps.max() > 0.2  # in steps ...
    assert np.allclose(poses[-1], there)  # ... to where the cloud is
    assert loc.recoveries == 0  # not a switch
    off, _, _ = _tracking_jump(stata, np.diag([1e-4, 1e-4, 1e-5]), jump_glide=0.0)
    assert np.hypot(*np.diff(off[:, :2], axis=0).T).max() > 0.6  # recovery_jump_glide 0: at once


def _update_moves_the_cloud(stata, truth, believed, moved, caplog):
    """A Localizer told it is at ``believed`` (tight) while the robot drives from ``truth`` at 0.5 m/s, its
    scans cast there; the second sensor update puts the whole cloud at ``moved`` (driven as far: a cloud
    whose weight moved there). The published estimates, and the Localizer."""
    loc = Localizer(params(num_particles=300, range_scale_estimation=False), logging.getLogger("test.refuse"))
    loc.set_map(stata)
    loc.set_initial_pose(believed, np.diag([1e-4, 1e-4, 1e-5]))
    caster, mount = ExactRayCaster(stata, 10.0), np.array([0.275, 0.0, 0.0])
    updates = []

    def counted(real_update):
        def update(*args, **kwargs):
            out = real_update(*args, **kwargs)
            updates.append(1)
            if len(updates) == 2:
                loc._pf.set_particles(np.tile(moved + [0.05 * len(poses) * math.cos(moved[2]),
                                                       0.05 * len(poses) * math.sin(moved[2]), 0.0], (300, 1)))
            return out
        return update

    wrap_sensor_updates(loc._pf, counted)
    poses = []
    with caplog.at_level(logging.WARNING, logger="test.refuse"):
        for k in range(10):
            t = 0.1 * k
            robot = truth + [0.05 * k * math.cos(truth[2]), 0.05 * k * math.sin(truth[2]), 0.0]
            laser = robot + [mount[0] * math.cos(robot[2]), mount[0] * math.sin(robot[2]), 0.0]
            loc.on_odometry(TwistData(t, 0.5, 0.0, 0.0))
            scan = ScanData(t, caster.cast(laser[None], ANGLES)[0], ANGLES[0], ANGLES[-1], INC, 0.02, 10.0)
            est = loc.on_scan(scan).estimate
            poses.append(est.pose if est is not None else poses[-1])
    return np.array(poses), loc


def test_an_update_that_jumps_to_a_place_the_scan_fits_worse_is_undone(stata, caplog):
    """The cloud's weight moves 0.6 m away, to a place the scan fits worse than the published pose: the
    update is undone (one log line), the pose goes on from where it was, without a jump."""
    truth = np.array([-6.6, 20.5, -2.24])
    wrong = truth + [0.6 * math.sin(truth[2]), -0.6 * math.cos(truth[2]), 0.0]  # 0.6 m to the side
    poses, loc = _update_moves_the_cloud(stata, truth, truth, wrong, caplog)
    assert loc.refused_jumps == 1 and "fits no clearly better" in caplog.text
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert steps.max() < 0.1  # 0.05 m per scan driven: no jump
    end = truth[:2] + 0.45 * np.array([math.cos(truth[2]), math.sin(truth[2])])
    assert np.hypot(*(poses[-1, :2] - end)) < 0.05  # still on the true track
    assert loc.recoveries == 0 and loc.status == "tracking"


def test_an_update_that_jumps_to_a_place_the_scan_fits_clearly_better_is_taken(stata, caplog):
    """The same move of the cloud, but the robot is there (its initial pose was 0.6 m off): the update is
    kept and the published estimate glides to it."""
    truth = np.array([-6.6, 20.5, -2.24])
    wrong = truth + [0.6 * math.sin(truth[2]), -0.6 * math.cos(truth[2]), 0.0]
    poses, loc = _update_moves_the_cloud(stata, truth, wrong, truth, caplog)
    assert loc.refused_jumps == 0 and "fits no clearly better" not in caplog.text
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert 0.2 < steps.max() <= loc.params.recovery_jump_glide + 0.05 + 1e-9  # glided (plus 0.05 m driven)
    end = truth[:2] + 0.45 * np.array([math.cos(truth[2]), math.sin(truth[2])])
    assert np.hypot(*(poses[-1, :2] - end)) < 0.05  # on the true track


def test_a_cloud_converging_from_a_wide_initial_pose_is_published_at_once(stata):
    # 0.6 m lies within three standard deviations of a 0.5 m initial pose: convergence, not a jump
    poses, there, _ = _tracking_jump(stata, np.diag([0.25, 0.25, 0.05]))
    assert np.allclose(poses[1], there)
