"""The child process of ``compile_cache.ensure_compiled``: run a localizer with the given parameters
on a tiny synthetic map through one odometry and one scan, so every kernel it uses is compiled
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
    """Run a localizer with ``params`` on ``tiny_map`` through one odometry and one scan."""
    from localization.core.localizer import Localizer
    from localization.core.odometry import TwistData
    from localization.core.parameters import Parameters
    from localization.core.scan import ScanData

    params = dict(params, num_particles=50, global_localization=False, adaptive_particles=False,
                  update_min_distance=0.0, update_min_angle=0.0)
    loc = Localizer(Parameters(params))
    occupancy_map = tiny_map()
    # the sensor model's own preparation (ensure_compiled points this process's table cache at a scratch
    # folder and leaves the compiling to it)
    loc.set_map(occupancy_map, loc.prepare_ray_caster(occupancy_map))
    loc.set_initial_pose(np.array([1.0, 1.0, 0.0]), stamp=0.0)
    loc.on_odometry(TwistData(0.0, 0.5, 0.0, 0.1))
    loc.on_odometry(TwistData(0.02, 0.5, 0.0, 0.1))
    n = 1081
    ranges = np.full(n, 1.0)
    inc = 4.71238898 / (n - 1)
    loc.on_scan(ScanData(0.02, ranges, -2.35619449, 2.35619449, inc, 0.02, 30.0))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    from localization.core.parameters import Parameters
    compile_kernels(Parameters(json.loads(argv[0]) if argv else {}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
