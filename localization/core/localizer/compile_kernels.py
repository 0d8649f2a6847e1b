"""The child process of ``compile_cache.ensure_compiled``: run a localizer with the given parameters
on a tiny synthetic map through a short drive (odometry and scans), so every kernel it uses is compiled
(with the very types the real run uses) into numba's on-disk cache, then exit.

    python -m localization.core.localizer.compile_kernels '<parameters as JSON>'
"""
from __future__ import annotations

import json
import sys

import numpy as np


def tiny_map():
    """A 60 × 60-cell room (0.05 m cells) with a pillar: the smallest map that exercises every kernel."""
    from localization.core.occupancy_map import OccupancyMap
    data = np.zeros((60, 60), dtype=np.int8)
    data[[0, -1], :] = data[:, [0, -1]] = 100
    data[25:35, 25:35] = 100
    return OccupancyMap(data=data, resolution=0.05, origin=(0.0, 0.0, 0.0))


def compile_kernels(params) -> None:
    """Run a localizer with ``params`` on ``tiny_map`` (512 particles: enough for two threads): a tight initial
    pose (so the cloud counts as converged and learns the range scale), then 0.6 s of driving with odometry at
    50 Hz and a scan ray cast in the map every 0.1 s. The odometry's stamps are shifted by ``odom_time_offset``,
    so that on the scan clock it covers the scans whatever the robot's calibration (with the car's +0.129 s the
    first scans came before any odometry and the motion kernel was never called: never cached)."""
    from localization.core.localizer import Localizer
    from localization.core.models.beam import MIN_PARTICLES_PER_THREAD
    from localization.core.odometry import TwistData
    from localization.core.parameters import Parameters
    from localization.core.raycast.exact import ExactRayCaster
    from localization.core.scan import ScanData
    # enough particles for two threads: with ``num_threads`` > 1 the threaded kernel runs too
    params = Parameters(dict(params), num_particles=2 * MIN_PARTICLES_PER_THREAD, global_localization=False,
                        adaptive_particles=False, update_min_distance=0.0, update_min_angle=0.0)
    loc = Localizer(params)
    occupancy_map = tiny_map()
    # the sensor model's own preparation (ensure_compiled points this process's table cache at a scratch
    # folder and leaves the compiling to it)
    loc.set_map(occupancy_map, loc.prepare_ray_caster(occupancy_map))
    speed, turn = 0.5, 0.1
    loc.set_initial_pose(np.array([0.8, 0.8, 0.0]), np.diag([1e-4, 1e-4, 1e-5]), stamp=0.0)
    n = 1081
    angles = np.linspace(-2.35619449, 2.35619449, n)
    caster = ExactRayCaster(occupancy_map, 25.0)
    for k in range(31):
        t = 0.02 * k
        loc.on_odometry(TwistData(t - params.odom_time_offset, speed, 0.0, turn))
        if k % 5 == 2:  # a scan between odometry messages, swept over 25 ms
            heading = turn * t
            pose = np.array([0.8 + speed * t * np.cos(heading / 2), 0.8 + speed * t * np.sin(heading / 2), heading])
            laser = pose + np.array([params.laser_offset_x * np.cos(heading), params.laser_offset_x * np.sin(heading),
                                     params.laser_offset_yaw])
            ranges = caster.cast(laser[None], angles)[0]
            loc.on_scan(ScanData(t, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 30.0,
                                 time_increment=0.025 / n))
    loc.flush()
    # what this drive may not reach: the compiled noise draws (none when deterministic without roughening), a
    # stack composed with one pose (the deskew's, off in some parameter files), a piece's covariance and factor as
    # a recovery's challenger plans them (piece by piece, from Python)
    from localization.core.draws import COMPILED_MIN_SIZE, standard_normal_into
    from localization.core.geometry import compose
    from localization.core.models.motion import MotionModel, noise_factor
    standard_normal_into(np.random.default_rng(0), np.empty(COMPILED_MIN_SIZE))
    compose(np.zeros((2, 3)), np.zeros(3))
    noise_factor(MotionModel().noise_covariance([0.1, 0.0, 0.05]))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    from localization.core.parameters import Parameters
    compile_kernels(Parameters(json.loads(argv[0]) if argv else {}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
