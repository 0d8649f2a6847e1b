"""Global seeder: how a global spread (start, ``initialize_global``, recovery) places its particles.

    uniform   N = global particle count poses uniform over the free space, headings uniform
    scan      the same spread, then, at the next scan, particles drawn around the lattice poses that
              scan fits best (``filter.global_init.seed_from_scan``), before that scan's own update

The global particle count is ``max_particles`` with ``adaptive_particles`` (KLD shrinks the cloud as it
converges), else ``global_num_particles``. While spread, the filter keeps that count (``kld_hold``).
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace

from localization.core.filter.global_init import ScanSeedParams, seed_from_scan
from localization.core.filter.mcl import MonteCarloLocalizer
from localization.core.occupancy_map import OccupancyMap


class GlobalSeeder:
    def __init__(self, params, log: logging.Logger):
        self.params, self.log = params, log
        self.pending = False  # the next scan seeds the spread (global_init scan)

    @property
    def count(self) -> int:
        p = self.params
        return p.max_particles if p.adaptive_particles else p.global_num_particles

    def spread(self, pf: MonteCarloLocalizer, occupancy_map: OccupancyMap) -> None:
        """Particles uniform over the free space; with global_init scan the next scan re-seeds them."""
        pf.resize(self.count)
        pf.initialize_uniform(occupancy_map)
        pf.hold_count(True)
        self.pending = self.params.global_init == "scan"

    def seed(self, pf: MonteCarloLocalizer, occupancy_map: OccupancyMap, ranges, angles, range_max: float) -> None:
        """global_init scan: replace the pending uniform spread by poses this scan fits."""
        if not self.pending:
            return
        self.pending = False
        t0 = time.perf_counter()
        seeds = seed_from_scan(occupancy_map, pf.sensor_model, ranges, angles, pf.num_particles, pf.rng,
                               ScanSeedParams.from_parameters(self.params), range_max=range_max)
        pf.set_particles(seeds.poses)
        pf.cost.cast("global_seed", seeds.lattice_poses * min(self.params.global_seed_beams, len(ranges)))
        self.log.info(f"global localization: {seeds.lattice_poses} lattice poses scored against the scan in "
                      f"{time.perf_counter() - t0:.2f} s; {len(seeds.poses)} particles drawn around the best "
                      f"{len(seeds.candidates)}")

    def converged(self, pf: MonteCarloLocalizer, pose) -> None:
        """The spread has converged: back to num_particles (KLD shrinks an adaptive cloud itself)."""
        pf.hold_count(False)
        if pf.kld is None:
            pf.resize(self.params.num_particles)
        self.log.info(f"global localization converged at ({pose[0]:.2f}, {pose[1]:.2f}, {pose[2]:.2f}): "
                      f"{pf.num_particles} particles")

    def challenger(self, pf: MonteCarloLocalizer, occupancy_map: OccupancyMap, ranges, angles,
                   range_max: float) -> MonteCarloLocalizer:
        """A second, small cloud of recovery_particles drawn where this scan fits the map (same models)."""
        params = replace(ScanSeedParams.from_parameters(self.params), global_seed_uniform=0.0)
        seeds = seed_from_scan(occupancy_map, pf.sensor_model, ranges, angles, self.params.recovery_particles,
                               pf.rng, params, range_max=range_max)
        cloud = MonteCarloLocalizer(pf.motion_model, pf.sensor_model, len(seeds.poses), pf.resample_ess_fraction,
                                    pf.roughening, pf.rng)
        cloud.cost = pf.cost.scoped("challenger")  # its beams and passes count as the challenger's (core.cost)
        cloud.cost.cast("global_seed", seeds.lattice_poses * min(self.params.global_seed_beams, len(ranges)))
        cloud.set_particles(seeds.poses)
        return cloud
