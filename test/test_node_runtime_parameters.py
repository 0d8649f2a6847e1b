"""Parameters set on the running node over DDS (the set_parameters services ros2 param / rqt use): applied
between updates, refused with the reason, read-only ones say why, a stream of changes during a drive."""
from __future__ import annotations

import threading

import numpy as np
import pytest

pytest.importorskip("rclpy")

import node_harness as h  # noqa: E402
from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters, SetParametersAtomically  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

NODE = "/particle_filter"


def _call(r, srv_type, name: str, request, timeout: float = 10.0):
    client = r.probe.create_client(srv_type, f"{NODE}/{name}")
    try:
        assert client.wait_for_service(timeout_sec=timeout), f"no {NODE}/{name} service"
        future = client.call_async(request)
        assert h.wait_until(future.done, timeout), f"{name} did not answer"
        return future.result()
    finally:
        r.probe.destroy_client(client)


def set_params(r, atomically: bool = False, **values) -> list:
    """Set parameters as ``ros2 param set`` does; the results (one per parameter, or one when atomic)."""
    msgs = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
    if atomically:
        return [_call(r, SetParametersAtomically, "set_parameters_atomically",
                      SetParametersAtomically.Request(parameters=msgs)).result]
    return list(_call(r, SetParameters, "set_parameters", SetParameters.Request(parameters=msgs)).results)


def get_param(r, name: str):
    from rclpy.parameter import parameter_value_to_python
    return parameter_value_to_python(_call(r, GetParameters, "get_parameters", GetParameters.Request(names=[name]))
                                     .values[0])


def _localizing(r, drive, seconds: float):
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    events = drive.until(seconds)
    r.play(events)
    return len(events)


def test_num_particles_set_during_a_drive_changes_the_published_cloud(runner, drive):
    r = runner(num_particles=500, max_particles_published=500)
    done = _localizing(r, drive, 0.8)
    assert h.wait_until(lambda: any(len(m.poses) == 500 for m in r.probe.snapshot()[1]), 5.0)
    [result] = set_params(r, num_particles=300)
    assert result.successful, result.reason
    assert h.wait_until(lambda: r.node.runtime.applied == 1, 5.0)
    r.probe.clear()
    r.play(drive.events[done:done + 40])
    r.settle()
    clouds = r.probe.snapshot()[1]
    assert clouds and {len(m.poses) for m in clouds} == {300}
    assert r.node.localizer.num_particles == 300 and get_param(r, "num_particles") == 300
    status = r.node.diagnostic_status()
    assert "num_particles 500 -> 300" in status.values["parameters changed"]


def test_an_invalid_value_is_refused_with_the_reason_and_changes_nothing(runner, drive):
    r = runner()
    done = _localizing(r, drive, 0.3)
    sigma = r.node.params.sigma_hit
    [result] = set_params(r, sigma_hit=-1.0)
    assert not result.successful and "sigma_hit=-1.0 must be" in result.reason
    [result] = set_params(r, alpha_hit=0.0, alpha_short=0.0, alpha_max=0.0, alpha_rand=0.0, atomically=True)
    assert not result.successful and "at least one of alpha_hit" in result.reason
    assert get_param(r, "sigma_hit") == sigma and r.node.params.sigma_hit == sigma and r.node.runtime.applied == 0
    # a parameter that cannot change while the node runs: read-only, and its descriptor says why
    [result] = set_params(r, scan_topic="/other_scan")
    assert not result.successful and "read-only" in result.reason
    described = _call(r, DescribeParameters, "describe_parameters",
                      DescribeParameters.Request(names=["scan_topic", "sigma_hit"])).descriptors
    assert described[0].read_only and "read-only while the node runs: read once when the node starts" in \
        described[0].description
    assert not described[1].read_only and "can change while the node runs" in described[1].description
    before = r.node.counts["scan"]
    r.play(drive.events[done:done + 20])  # still running
    assert r.node.counts["scan"] > before and np.all(np.isfinite(r.node.localizer.estimate.pose))


def test_a_stream_of_changes_during_a_drive_loses_no_scan_and_publishes_no_nan(runner, drive, tmp_path, monkeypatch):
    from localization.core.raycast import lookup_table
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))  # the range table below is built, not loaded
    monkeypatch.setattr(lookup_table, "LIVE_TABLES", {})
    r = runner(num_particles=400, max_particles_published=400)
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    changes = [dict(num_particles=300), dict(sigma_hit=0.25), dict(motion_a_trans=0.2, motion_floor_xy=0.01),
               dict(ray_caster="lookup_table", scan_theta_discretization=16), dict(num_particles=450),
               dict(do_beamskip=True), dict(squash_factor=3.0), dict(odom_timeout=0.8),
               dict(num_beams_per_particle=80), dict(sigma_hit=-5.0), dict(num_particles=350)]
    results = []

    def stream():
        for values in changes:
            results.append(set_params(r, atomically=True, **values)[0])
    setter = threading.Thread(target=stream, daemon=True)
    setter.start()
    scans = sum(1 for _, kind, _ in drive.events if kind == "scan")
    r.play(drive.events)  # lock-step: each scan is handled before the next is sent
    setter.join(30.0)
    assert not setter.is_alive() and len(results) == len(changes)
    assert r.node.counts["scan"] == scans  # every scan handled, none lost
    accepted = sum(res.successful for res in results)
    assert accepted == len(results) - 1 and not results[changes.index(dict(sigma_hit=-5.0))].successful
    assert h.wait_until(lambda: r.node.runtime.applied == accepted, 60.0)  # the range table too
    r.settle()
    poses, clouds, _ = r.probe.snapshot()
    values = [m.pose.pose.position.x for m in poses] + [p.position.x for m in clouds for p in m.poses]
    assert values and np.all(np.isfinite(values))
    assert np.all(np.isfinite(r.node.localizer.particles()))
    p = r.node.params
    assert (p.ray_caster, p.scan_theta_discretization, p.num_particles, p.sigma_hit) == ("lookup_table", 16, 350, 0.25)
    assert r.node.watchdog.odom_timeout == 0.8
