"""The simulator's perturbed world (``perturb_map``): the lidar sees boxes, people, glass and a scale error
the filter's map does not have, the planned path stays clear, the truth is scored in the map frame
(``world_to_map``: q = c + (p − c) / s), and the filter still tracks the car at 2 m/s."""
from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from localization.core.localizer import Localizer
from localization.core.occupancy_map import load_map
from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.datasets import trial_config
from localization.eval.feed import Feeder, recording_events
from localization.eval.metrics import compare_to_truth, false_recoveries
from localization.sim import recorder as S
from localization.sim.perturb import STANDARD_PERTURBATION, MapPerturbation, perturb_map, world_to_map
from localization.sim.trajectory import simulate_trajectory

WORLD = STANDARD_PERTURBATION  # 6 boxes, 4 people, 5 % glass, scale 1.01
_CACHE = {}


def stata():
    if "map" not in _CACHE:
        _CACHE["map"] = load_map("stata_basement")
    return _CACHE["map"]


def drive(world):
    """A 12 s, 2 m/s drive of trial 2 (odometry noise 0.3) with the lidar in ``world``."""
    return replace(trial_config("trial2_noise0.3", duration=12.0, speed=2.0), world=world)


def test_perturb_map_changes_cells_but_keeps_the_path_clear():
    m = stata()
    path = simulate_trajectory(drive(None), m).poses[:, :2]
    world = perturb_map(m, replace(WORLD, scale=1.0), keep_free=path)
    assert world.data.shape == m.data.shape and world.origin == m.origin
    added = world.occupied & ~m.occupied
    glass = m.occupied & ~world.occupied
    assert added.sum() > 6 * 50  # six boxes (≥ 0.4 m squares) and four people
    assert glass.sum() > 0.02 * m.occupied.sum()  # some of the walls are glass
    on_path = np.zeros(m.data.shape, dtype=bool)
    cr = m.world_to_grid(path)
    on_path[cr[:, 1], cr[:, 0]] = True
    clear = distance_transform_edt(~on_path) * m.resolution <= WORLD.clearance
    assert np.array_equal(world.data[clear], m.data[clear])  # the clearance keeps the map's cells
    assert not world.occupied[clear & m.free].any()
    assert np.array_equal(m.data, load_map("stata_basement").data)  # the input is unchanged


def test_scale_scales_the_world_about_the_kept_points():
    m = stata()
    centre = np.array([[-6.4, 20.3]])
    world = perturb_map(m, MapPerturbation(scale=1.02, clearance=0.0), keep_free=centre)
    # a wall point q of the map appears at c + 1.02 (q − c) in the world
    walls = m.grid_to_world(np.argwhere(m.occupied)[::97, ::-1])
    far = np.hypot(*(walls - centre).T) > 10.0
    moved = centre + 1.02 * (walls[far] - centre)
    assert world.is_occupied_or_outside(moved).mean() > 0.95
    assert m.is_occupied_or_outside(moved).mean() < 0.5  # 1.02 moves them 0.2 m or more: off the map's walls
    assert np.array_equal(perturb_map(m, MapPerturbation()).data, m.data)


def test_world_to_map_scales_a_point_back_about_the_centre():
    c = np.array([-6.4, 20.3])
    p = np.array([[c[0] + 10.2, c[1] - 5.1, 0.7]])  # 11.4 m from c
    q = world_to_map(p, 1.02, c)
    assert q[0, :2] == pytest.approx(c + np.array([10.0, -5.0]))  # c + (p − c) / 1.02
    assert q[0, 2] == 0.7  # the heading is unchanged
    assert np.hypot(*(q[0, :2] - p[0, :2])) == pytest.approx((1 - 1 / 1.02) * np.hypot(10.2, 5.1))
    assert np.array_equal(world_to_map(p, 1.0, c), p)  # scale 1: the very poses
    assert np.array_equal(p, [[c[0] + 10.2, c[1] - 5.1, 0.7]])  # the input is unchanged


def test_a_recording_carries_the_truth_in_the_map_frame():
    m = stata()
    cfg = replace(drive(replace(WORLD, scale=1.02)), duration=2.0)
    rec = S.simulate(cfg, m)
    c = rec.trajectory.poses[:, :2].mean(axis=0)  # the planned path's centroid
    assert rec.scale_centre == pytest.approx(c)
    assert np.array_equal(rec.world_truth_poses, rec.trajectory.poses[np.rint(rec.truth_t * 200).astype(int)])
    assert rec.truth_poses[:, :2] == pytest.approx(c + (rec.world_truth_poses[:, :2] - c) / 1.02)
    assert np.array_equal(rec.truth_poses[:, 2], rec.world_truth_poses[:, 2])
    clean = S.simulate(replace(cfg, world=None), m)
    assert clean.world_truth_poses is clean.truth_poses and clean.scale_centre is None
    assert np.array_equal(clean.truth_poses, rec.world_truth_poses)  # the same drive


def localize(cfg, seed: int = 1, **overrides) -> dict:
    """``cfg`` localized with config/params.yaml (and parameter ``overrides``) from its /initialpose, scored after
    the first second: mean position error against the truth in the map frame ("map") and against the world-frame
    truth ("world") (m), Localizer recoveries, false recoveries (switches to a place > 1 m from the map-frame
    truth), the range scale in use at the end. The sensor update runs on every core (the same weights bit for bit
    as on one). Cached: the tests below share runs."""
    key = (cfg.key(), seed, tuple(sorted(overrides.items())))
    if key in _CACHE:
        return _CACHE[key]
    rec = S.simulate(cfg, stata())
    loc = Localizer(Parameters.from_yaml(config_dir() / "params.yaml", random_seed=seed,
                                         **{"num_threads": os.cpu_count() or 1, **overrides}))
    loc.set_map(stata())
    loc.set_initial_pose(rec.initial_pose, stamp=-0.001)
    feeder = Feeder(loc)
    feeder.feed(recording_events(rec))
    t, poses = feeder.log.estimates()
    err = compare_to_truth(t, poses, rec.truth_t, rec.truth_poses)
    world = compare_to_truth(t, poses, rec.truth_t, rec.world_truth_poses)
    _CACHE[key] = {"map": float(err.ct_error[err.t > 1.0].mean()), "world": float(world.ct_error[world.t > 1.0].mean()),
                   "recoveries": loc.recoveries, "false_recoveries": false_recoveries(err.t, err.ct_error, t_start=0.0),
                   "range_scale": loc.range_scale}
    return _CACHE[key]


def test_the_filter_tracks_a_drive_in_the_unscaled_perturbed_world():
    cfg = drive(replace(WORLD, scale=1.0))
    assert cfg.key() != drive(None).key() and drive(None).key() == trial_config(
        "trial2_noise0.3", duration=12.0, speed=2.0).key()
    r = localize(cfg)
    assert r["recoveries"] == 0 and r["false_recoveries"] == 0
    assert r["map"] <= 0.03 and r["world"] == r["map"]  # no scale error: one truth


def test_the_filter_tracks_a_2mps_drive_in_the_standard_perturbed_world():
    r = localize(drive(WORLD))  # scale 1.01
    assert r["recoveries"] == 0 and r["false_recoveries"] == 0
    assert r["map"] <= 0.03  # in the map frame: the error a localizer in the map can remove
    assert r["world"] > r["map"] + 0.02  # the world-frame figure adds (1 − 1/s)·|p − c|


def test_with_the_range_scale_fixed_a_2_percent_scale_error_costs_accuracy_but_no_false_recovery():
    fixed = localize(drive(replace(WORLD, scale=1.02)), range_scale_estimation=False)
    assert fixed["recoveries"] == 0 and fixed["false_recoveries"] == 0
    assert 0.03 < fixed["map"] <= 0.05  # the beam model's best fit lies behind the car (docs/performance.md)


def test_a_calibrated_range_scale_removes_the_conflict_at_scale_1_02():
    # lidar_scale_to_map_scale = 1/s: the correction localization-calibrate estimates on a real car
    r = localize(drive(replace(WORLD, scale=1.02)), lidar_scale_to_map_scale=1 / 1.02, range_scale_estimation=False)
    assert r["recoveries"] == 0 and r["false_recoveries"] == 0
    assert r["map"] <= 0.03


def test_the_range_scale_learnt_online_follows_a_building_2_percent_larger_than_its_map():
    # config/params.yaml learns the scale while the filter tracks: no calibration
    r = localize(drive(replace(WORLD, scale=1.02)))
    assert r["recoveries"] == 0 and r["false_recoveries"] == 0
    assert r["map"] <= 0.03
    assert r["range_scale"] == pytest.approx(1 / 1.02, abs=0.004)  # started at 1.0


def test_the_range_scale_learnt_online_stays_at_one_where_the_world_matches_the_map_scale():
    r = localize(drive(replace(WORLD, scale=1.0)))
    assert r["recoveries"] == 0 and r["false_recoveries"] == 0 and r["map"] <= 0.03
    assert r["range_scale"] == pytest.approx(1.0, abs=0.003)


def test_the_whole_route_at_2mps_in_a_building_2_percent_larger_than_its_map():
    r = localize(replace(trial_config("trial2_noise0.3", speed=2.0), world=replace(WORLD, scale=1.02)))
    assert r["recoveries"] == 0 and r["false_recoveries"] == 0
    assert r["map"] <= 0.03


def test_beam_skipping_keeps_the_whole_route_within_3_cm_in_a_perturbed_world_it_was_not_chosen_on():
    # do_beamskip (config/params.yaml) was chosen on the perturbation of seed 1; seed 2 puts the glass, boxes and
    # people elsewhere. Without it the readings through glass pull the estimate along the corridor.
    cfg = replace(trial_config("trial2_noise0.3", speed=2.0), world=replace(WORLD, seed=2))
    skipping, plain = (localize(cfg, range_scale_estimation=False, do_beamskip=v) for v in (True, False))
    for r in (skipping, plain):
        assert r["recoveries"] == 0 and r["false_recoveries"] == 0
    assert skipping["map"] <= 0.03 < plain["map"]


if __name__ == "__main__":  # the figures: errors without and with the perturbation, by scale; range scale online
    import sys
    whole = "--whole" in sys.argv  # the whole of trial 2 at 2 m/s instead of the 12-s drive

    def run(world):
        return replace(trial_config("trial2_noise0.3", speed=2.0), world=world) if whole else drive(world)
    for world in (None, *(replace(WORLD, scale=s) for s in (1.0, 1.01, 1.02))):
        print(world, localize(run(world)))
        if world is not None:
            print("  range scale fixed", localize(run(world), range_scale_estimation=False))
    for seed in (1, 2, 3):
        world = replace(WORLD, seed=seed)
        print(f"perturbation seed {seed}:", localize(run(world)), "scale fixed: beam skipping",
              localize(run(world), range_scale_estimation=False), "without",
              localize(run(world), range_scale_estimation=False, do_beamskip=False))
    for s in (1.01, 1.02):
        print(f"scale {s}, lidar_scale_to_map_scale 1/{s}",
              localize(run(replace(WORLD, scale=s)), lidar_scale_to_map_scale=1 / s, range_scale_estimation=False))
    print("scale 1.01 without glass", localize(run(replace(WORLD, scale=1.01, glass_fraction=0.0))))
