"""An initial pose before the map is handled as one after it: it waits for the map, then is checked
against it (a pose off the map snapped to the nearest free cell, with one warning), never a silent
wait. In the core, and over DDS through the node in both orders."""
from __future__ import annotations

import logging

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.localizer import Localizer
from localization.core.parameters import Parameters

OFF_MAP = np.array([500.0, 500.0, 0.3])  # far outside any map here (localization-play --initial-pose=500,500,0)


def _localizer() -> Localizer:
    return Localizer(Parameters(num_particles=200, random_seed=4, ray_caster="distance_transform"))


@pytest.mark.parametrize("pose", [OFF_MAP, np.array([5.0, 0.52, 0.0])], ids=["off the map", "in a wall"])
def test_a_pose_before_the_map_ends_where_one_after_it_ends(pose, caplog):
    occupancy_map = corridor_map()
    before, after = _localizer(), _localizer()
    with caplog.at_level(logging.INFO):
        assert before.set_initial_pose(pose, None, 1.0)  # kept, not refused
        assert not before.ready and "initial pose kept until a map arrives" in caplog.text
        before.set_map(occupancy_map)
    waited = caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO):
        after.set_map(occupancy_map)
        assert after.set_initial_pose(pose, None, 1.0)
    assert before.ready and after.ready
    np.testing.assert_array_equal(before.particles(), after.particles())
    np.testing.assert_array_equal(before.estimate.pose, after.estimate.pose)
    snapped = occupancy_map.nearest_free(pose[:2])  # where a pose after the map is moved to
    assert np.hypot(*(before.particles()[:, :2].mean(axis=0) - snapped)) < 0.5
    for text in (waited, caplog.text):
        assert text.count("is not in free space: moved to the nearest free cell") == 1
        assert "waiting for a new initial pose" not in text


def test_a_pose_that_is_not_finite_is_refused_at_once_without_a_map(caplog):
    loc = _localizer()
    with caplog.at_level(logging.WARNING):
        assert loc.set_initial_pose([np.nan, 1.0, 0.0]) is False
    assert "not finite" in caplog.text
    loc.set_map(corridor_map())
    assert not loc.ready  # nothing was kept for the map


# ------------------------------------------------------------------ over DDS, both orders
def _node_run(runner, drive, pose_first: bool):
    import node_harness as h
    r = runner()
    pose, grid = h.initialpose_msg(OFF_MAP), h.map_msg("stata_basement")
    if pose_first:
        r.send_initialpose(pose)
        assert not r.node.localizer.ready  # kept for the map
        r.send_map(grid)
    else:
        r.send_map(grid)
        r.send_initialpose(pose)
    assert r.node.localizer.ready
    particles = r.node.localizer.particles()
    r.play(drive.until(0.3))
    r.settle()
    poses = r.probe.snapshot()[0]
    r.close()  # the next run's node has the same name: this one must not hear its inputs
    return particles, poses


def test_over_dds_either_order_gives_the_same_cloud_and_the_node_localizes(runner, drive, capfd):
    pytest.importorskip("rclpy")
    import node_harness as h
    first, poses_first = _node_run(runner, drive, pose_first=True)
    log_first = capfd.readouterr().err
    second, poses_second = _node_run(runner, drive, pose_first=False)
    log_second = capfd.readouterr().err
    np.testing.assert_array_equal(first, second)  # the same seed, the same snapped pose: the same cloud
    snapped = h.load_map("stata_basement").nearest_free(OFF_MAP[:2])
    assert np.hypot(*(first[:, :2].mean(axis=0) - snapped)) < 0.5  # around the nearest free cell
    for poses in (poses_first, poses_second):  # no silent wait: poses are published in both orders
        assert len(poses) > 5
        xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in poses])
        assert np.all(np.isfinite(xy))
    np.testing.assert_allclose([poses_first[0].pose.pose.position.x, poses_first[0].pose.pose.position.y],
                               [poses_second[0].pose.pose.position.x, poses_second[0].pose.pose.position.y],
                               atol=1e-9)
    assert "initial pose kept until a map arrives" in log_first
    for log in (log_first, log_second):
        assert log.count("is not in free space: moved to the nearest free cell") == 1, log
        assert "waiting for a new initial pose" not in log
