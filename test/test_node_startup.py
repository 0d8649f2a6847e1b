"""A live start that never lies: one range table per map content (YAML or DDS), /diagnostics WARN
or ERROR while scans are dropped or the filter is lost, output stamps that only move forward, and
the documented cold start (node + ``localization-play``) ending where ``localization-replay`` ends."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")

import node_harness as h  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from localization.core.occupancy_map import OccupancyMap  # noqa: E402
from localization.core.watchdog import ERROR, OK, WARN, Watchdog  # noqa: E402
from localization.ros.messages import occupancy_grid_msg  # noqa: E402

COLD_BAG = "rss2022/localization_bag1_2022-03-29-19-23-29.bag"
COLD_RUNS = 2  # one cold start, one that loads its table; five cold runs are the benchmark's
FINAL_TOLERANCE_M = 0.1


def _over_dds(occupancy_map: OccupancyMap) -> OccupancyMap:
    """The map as a node receives it: serialized (float32 resolution, yaw as a quaternion) and back."""
    from nav_msgs.msg import OccupancyGrid
    return OccupancyMap.from_msg(deserialize_message(serialize_message(occupancy_grid_msg(occupancy_map)),
                                                     OccupancyGrid))


# ------------------------------------------------------------------ one range table per map content
def test_a_map_received_over_dds_uses_the_yaml_maps_range_table(tmp_path, monkeypatch):
    from localization.core.raycast import lookup_table
    from localization.core.raycast.table_cache import cache_file_name
    monkeypatch.setattr(lookup_table, "LIVE_TABLES", {})
    rng = np.random.default_rng(3)
    data = np.where(rng.random((60, 80)) < 0.1, 100, 0).astype(np.int8)
    data[[0, -1], :] = 100
    yaml_map = OccupancyMap(data, 0.0504, (25.9, 48.5, 3.14))  # basement_fixed's resolution and origin
    dds_map = _over_dds(yaml_map)
    assert dds_map.resolution != yaml_map.resolution  # 0.05040000006556511: a float32 on the wire
    assert dds_map.digest == yaml_map.digest
    r_yaml, r_dds = 200 * yaml_map.resolution, 200 * dds_map.resolution  # the beam model's z_max in metres
    assert cache_file_name(dds_map, r_dds, 16) == cache_file_name(yaml_map, r_yaml, 16)
    built = lookup_table.LookupTableRayCaster.for_map(yaml_map, r_yaml, 16, cache_dir=tmp_path)
    assert built.table_source == "built" and len(list(tmp_path.iterdir())) == 1
    lookup_table.LIVE_TABLES.clear()
    loaded = lookup_table.LookupTableRayCaster.for_map(dds_map, r_dds, 16, cache_dir=tmp_path)
    assert loaded.table_source == "disk"  # the cached file, not a second build
    np.testing.assert_array_equal(loaded.table, built.table)
    # a different map still gets its own table
    other = OccupancyMap(data, 0.05, (25.9, 48.5, 3.14))
    assert other.digest != yaml_map.digest


def test_shipped_map_has_one_digest_as_yaml_and_as_message():
    m = h.load_map("basement_fixed")
    assert _over_dds(m).digest == m.digest


# ------------------------------------------------------------------ diagnostics that do not say OK wrongly
def _watchdog_with_input(health_lost_floor: float) -> Watchdog:
    """A watchdog with a map and 1 s of scans and odometry at 40 Hz (time 0 to 0.975 s)."""
    w = Watchdog(0.0, health_lost_floor=health_lost_floor)
    w.map_ready(0.0)
    for k in range(40):
        w.scan_received(k * 0.025)
        w.odom_received(k * 0.025)
    return w


def test_watchdog_errors_below_the_lost_floor_and_warns_while_scans_are_dropped():
    w = _watchdog_with_input(0.35)
    now = 1.0
    assert w.status(now, ready=True, health=0.9).level == OK
    assert w.status(now, ready=True, health=math.nan).level == OK  # no agreement yet (a global spread)
    lost = w.status(now, ready=True, health=0.23)
    assert lost.level == ERROR and "health_lost_floor" in lost.message and "0.23" in lost.message
    w.scans_not_used(now, 3, "while the range table was prepared")
    st = w.status(now, ready=True, health=0.9)
    assert st.level == WARN and "3 scans not used" in st.message and "range table" in st.message
    assert st.values["scans dropped"] == "3"
    assert w.status(now + 6.0, ready=True, health=0.9).problems == [] or \
        "scans-dropped" not in {p.key for p in w.status(now + 6.0, ready=True, health=0.9).problems}


def test_watchdog_warns_while_the_scans_disagree_with_the_map():
    w = _watchdog_with_input(0.25)
    assert w.status(1.0, ready=True, health=0.9).level == OK
    st = w.status(1.0, ready=True, health=0.4, holding=True)  # holding on odometry, above the lost floor
    assert st.level == WARN and st.problems[0].key == "disagree" and "scans disagree with the map" in st.message
    assert "0.40" in st.message
    st = w.status(1.0, ready=True, health=0.1, holding=True)  # and below the floor: ERROR first, the WARN with it
    assert st.level == ERROR and [p.key for p in st.problems][:2] == ["lost", "disagree"]
    assert w.status(1.0, ready=False, holding=True).level == OK  # not localizing: nothing to disagree with


def test_node_diagnostics_report_the_scans_it_cannot_use(runner, drive):
    r = runner()
    r.send_map(h.map_msg("stata_basement"))
    scans = [msg for _, kind, msg in drive.until(0.2) if kind == "scan"]
    for msg in scans:  # no initial pose yet: not usable
        r.send_scan(msg)
    status = r.node.diagnostic_status()
    assert status.level == WARN and f"{len(scans)} scans not used" in status.message
    assert "initial pose" in status.message and r.node.watchdog.scans_dropped == len(scans)


def test_diagnostics_log_an_error_then_a_warning_without_crashing(runner, monkeypatch, capfd):
    """A lost ERROR, then a WARN: both logged (rclpy refuses one logging call site with two severities)."""
    from localization.core.watchdog import Problem, Status
    r = runner()
    statuses = iter([Status(ERROR, "lost", problems=[Problem("lost", ERROR, "lost: agreement 0.10")]),
                     Status(WARN, "dropped", problems=[Problem("scans-dropped", WARN, "3 scans not used")])])
    monkeypatch.setattr(r.node, "diagnostic_status", lambda: next(statuses))
    r.node.publish_diagnostics()
    r.node.publish_diagnostics()
    err = capfd.readouterr().err
    assert "ERROR: lost: agreement 0.10" in err and "WARN: 3 scans not used" in err


# ------------------------------------------------------------------ stamps only move forward
def test_output_stamps_are_the_times_they_describe_and_never_go_back(runner, drive):
    """/pf/pose/odom and TF at each odometry message's corrected time t_k + odom_time_offset, /pf/pose at
    each scan's time: every stream strictly increasing."""
    offset = 0.012  # s
    r = runner(odom_time_offset=offset)
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    r.play(drive.events)
    r.settle()
    poses, _, tfs = r.probe.snapshot()
    corrections = r.probe.corrections_snapshot()
    odom_t = np.array([t for t, kind, _ in drive.events if kind == "odom"]) * 1e-9 + offset
    scan_t = np.array([t for t, kind, _ in drive.events if kind == "scan"]) * 1e-9
    pose_t = np.array([h.stamp_sec(m.header.stamp) for m in poses])
    corr_t = np.array([h.stamp_sec(m.header.stamp) for m in corrections])
    tf_t = np.array([h.stamp_sec(t.header.stamp) for t in tfs])
    assert len(pose_t) >= len(odom_t) - 2 and len(corr_t) > 20 and len(tf_t) == len(pose_t)
    for t in (pose_t, corr_t, tf_t):
        assert np.all(np.diff(t) > 0)
    assert np.abs(pose_t[:, None] - odom_t[None, :]).min(axis=1).max() < 1e-6  # an odometry message's t'_k
    assert np.abs(corr_t[:, None] - scan_t[None, :]).min(axis=1).max() < 1e-6  # a scan's time


# ------------------------------------------------------------------ the documented cold start
def test_cold_start_over_dds_ends_where_replay_ends(shared_dir):
    """``particle_filter --ros-args --params-file real_params`` started with an empty range-table
    cache, then ``localization-play BAG --map basement_fixed --initial-pose 0.8,-0.3,1.26``: the
    final pose on /pf/pose/odom is within 0.1 m of localization-replay's, its stamps never go back,
    and the node exits 0 on SIGINT. COLD_RUNS runs: the first cold (the range table built from the
    map received over DDS), the others load the table it cached (five cold runs:
    ``python -m localization.benchmarks.cold_start``, figures in docs/node.md)."""
    from localization.benchmarks.cold_start import run
    results, _ = run(runs=COLD_RUNS, warm_after_first=True, rate=2.0, bag=shared_dir / "bags" / COLD_BAG,
                     say=lambda _: None)
    first = results[0]
    assert first.cold and first.table_build_s is not None, first.node_log  # built: a real cold start
    assert all(r.table_build_s is None for r in results[1:])  # the cached table is found by the next starts
    for r in results:
        assert r.node_exit == 0 and r.play_exit == 0, (r.node_log[-3000:], r.play_log)
        assert r.ready_after_s is not None, r.play_log  # play waited for the node
        assert r.poses > 300 and r.stamps_monotonic, r
        assert r.error_m is not None and r.error_m < FINAL_TOLERANCE_M, r
        assert "0 not used" in r.node_log, r.node_log[-2000:]  # every scan of the bag used
