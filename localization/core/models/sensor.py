"""Sensor models: how likely a scan is from each particle's pose.

Every model implements ``SensorModel`` below (as nav2_amcl's ``sensors/laser`` siblings and
Beluga's sensor models do), so the filter, global initialisation, health checks, replay and the
benchmarks treat them alike and never look inside one:

    model.preparation(map)            # Preparation(slow, note): will prepare() take seconds?
    prepared = model.prepare(map)     # the slow part (range table, distance field); any thread
    model.set_map(map, prepared)      # use it (prepared=None: prepare here)
    model.set_laser_offset((x, y, yaw))                  # the laser pose in base_link
    model.log_likelihood(particles, ranges, angles, offsets=None, range_max=None)
                                      # (N,) squashed log weights, -inf = impossible
    model.last_beams_used             # beams the last log_likelihood used (beam skipping leaves some out)
    with model.scratch(): ...         # temporary memory (a tiled table's tiles) given back at the end
    model.range_probe(angles, offsets, range_max)   # RangeProbe: what learning the range scale needs
    model.set_range_scale(s)          # use s as lidar_scale_to_map_scale (supports_range_scale models)

z_max, the range of a "no return" reading (metres), is the sensor's: ``laser_max_range`` when it
is > 0, else the scan's own ``range_max`` (``log_likelihood(..., range_max=)``), else the model's
fallback (``max_range``); ``resolve_max_range`` is that rule.

``beam.BeamModel``: the course's beam model (p_hit, p_short, p_max, p_rand) over ray-cast
expected ranges, tabulated. ``likelihood_field.LikelihoodFieldModel``: nav2_amcl's likelihood
field (each beam's end point scored by its distance to the nearest occupied cell; no ray casting).
Only the beam model casts ranges, so only it can learn the lidar-to-map range scale online
(``supports_range_scale``; ``core.localizer.range_scale``); the likelihood field declares it does not.
The ``sensor_model`` parameter picks one (``localizer.build_filter``); docs/models.md compares them.

Beam skipping (``do_beamskip``, nav2_amcl's rule, both models): a return from something the map does not
have (a person, a box, a window the beam passes through) agrees with the map for few particles. With
v_b the particles for which beam b agrees with the map (the model says what "agrees" means) and V the
particles that can see (not off the map, not in a wall):

    used_b = v_b / V > beam_skip_threshold
    every beam is used when the skipped ones reach beam_skip_error_threshold of them (the cloud is off)

The same beams are used for every particle (``beam_mask``), so skipping never favours one. It applies
only while the cloud is one hypothesis (``skips_beams``: position standard deviation at most
``beam_skip_max_spread``): in a cloud that holds several (global localization, a recovery's
challengers) the beam that only the right one explains is a minority beam, and skipping it would
remove the very evidence that decides between them.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np


class LaserMount:
    """The laser pose in base_link, kept in a model's frozen ``params`` (laser_offset_x/_y/_yaw): read
    as a copy, changed only through ``set_laser_offset`` (both models share this)."""

    @property
    def laser_offset(self) -> np.ndarray:
        """(3,) the laser pose (x, y, yaw) in base_link (a copy)."""
        p = self.params
        return np.array([p.laser_offset_x, p.laser_offset_y, p.laser_offset_yaw], dtype=float)

    def set_laser_offset(self, offset) -> None:
        """Use the laser pose ``offset`` (x m, y m, yaw rad) in base_link."""
        x, y, yaw = (float(v) for v in np.asarray(offset, dtype=float).reshape(3))
        self.params = replace(self.params, laser_offset_x=x, laser_offset_y=y, laser_offset_yaw=yaw)


@dataclass(frozen=True)
class Preparation:
    """What ``prepare(map)`` will cost, known before it runs."""

    slow: bool  # seconds of work (a range table to build): prepare off the caller's thread
    note: str  # one line for the log, e.g. "range table: loading it from the cache for the map ..."


@dataclass(frozen=True)
class RangeProbe:
    """What learning the lidar-to-map range scale from one scan's beams needs (``core.localizer.range_scale``)."""

    cast: Callable[[np.ndarray], np.ndarray]  # poses (k, 3) -> (k, B) the beams' ranges ray cast (map metres)
    z_max: float  # lidar metres: a return at or beyond it is no return
    reach: float  # map metres: the farthest range the model casts
    wall_depth: float  # m: how far behind a wall's edge a beam ends (map_wall_depth)


def sweep_offsets(offsets, num_beams: int):
    """``offsets`` as (``num_beams``, 3) per-beam deskew offsets, or None (a rigid scan) when there are
    none, they are all zero (no motion during the sweep) or unusable (wrong count, non-finite)."""
    if offsets is None:
        return None
    offsets = np.asarray(offsets, dtype=float).reshape(-1, 3)
    if offsets.shape[0] != num_beams or not offsets.any() or not np.all(np.isfinite(offsets)):
        return None
    return offsets


def skips_beams(particles: np.ndarray, params) -> bool:
    """Whether beam skipping applies to ``particles`` (N, 3) under a model's ``params``: ``do_beamskip`` and the
    larger standard deviation of their finite x and y at most ``beam_skip_max_spread`` (m)."""
    if not params.do_beamskip:
        return False
    xy = np.asarray(particles, dtype=float)[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    return len(xy) > 0 and float(xy.std(axis=0).max()) <= params.beam_skip_max_spread


def beam_mask(params, votes: np.ndarray, voters: int) -> np.ndarray:
    """(B,) the beams used by beam skipping (module docstring) under a model's ``params``: ``votes`` (B,)
    particles agreeing on each beam out of ``voters``; all beams when nobody votes or the skipped ones reach
    ``beam_skip_error_threshold``."""
    votes = np.asarray(votes)
    if voters == 0:
        return np.ones(votes.size, dtype=bool)
    mask = votes / voters > params.beam_skip_threshold
    if votes.size - mask.sum() >= votes.size * params.beam_skip_error_threshold:
        return np.ones(votes.size, dtype=bool)
    return mask


def resolve_max_range(laser_max_range: float, range_max: float | None, fallback: float) -> float:
    """z_max (m): ``laser_max_range`` when > 0, else the scan's ``range_max`` when finite and > 0,
    else ``fallback``."""
    if laser_max_range > 0:
        return float(laser_max_range)
    if range_max is not None and math.isfinite(range_max) and range_max > 0:
        return float(range_max)
    return float(fallback)


@runtime_checkable
class SensorModel(Protocol):
    """What the filter, global initialisation and the node need of a sensor model."""

    params: Any  # the model's frozen parameter dataclass
    supports_deskew: bool  # log_likelihood takes per-beam laser offsets (a deskewed sweep)
    supports_range_scale: bool  # casts ranges: the lidar-to-map range scale can be learnt online
    last_beams_used: int | None  # beams the last log_likelihood used (beam skipping leaves some out; None: none yet)

    @property
    def laser_offset(self) -> np.ndarray:
        """(3,) the laser pose (x m, y m, yaw rad) in base_link (a copy)."""
        ...

    def set_laser_offset(self, offset) -> None:
        """Use the laser pose ``offset`` (x, y, yaw) in base_link, e.g. read from TF."""
        ...

    @property
    def max_range(self) -> float:
        """z_max (m) when the scan gives none: ``laser_max_range`` if > 0, else the model's fallback."""
        ...

    def preparation(self, occupancy_map) -> Preparation:
        """Whether ``prepare(occupancy_map)`` will be slow, and a one-line note for the log."""
        ...

    def prepare(self, occupancy_map) -> Any:
        """The slow part of ``set_map`` (a range table built or loaded, a distance field), without
        touching the model: safe on another thread."""
        ...

    def set_map(self, occupancy_map, prepared=None) -> None:
        """Use a (new) map, with what ``prepare`` returned for it (None: prepare here)."""
        ...

    def log_likelihood(self, particles, ranges, angles, offsets=None, range_max=None) -> np.ndarray:
        """(N,) squashed log weights of the beams (``ranges`` m at ``angles`` rad, laser frame);
        -inf for impossible particles. ``offsets`` (B, 3): per-beam laser motion of a deskewed sweep
        (ValueError from a model without ``supports_deskew``); ``range_max``: the scan's own (m)."""
        ...

    def scratch(self) -> AbstractContextManager:
        """A scope for temporary memory: what an evaluation inside it prepares (a tiled range
        table's tiles) is given back when it ends. A no-op for models without such memory."""
        ...

    def locality_order(self, xy) -> np.ndarray:
        """A permutation of world positions (K, 2) that keeps consecutive ones in the same prepared
        memory (a tiled table's tile): score them in this order inside ``scratch`` scopes. The
        identity for models without such memory."""
        ...

    def range_probe(self, angles, offsets=None, range_max=None) -> RangeProbe:
        """What learning the range scale from the beams at ``angles`` (rad; ``offsets`` (B, 3) a deskewed
        sweep's, ``range_max`` the scan's, m) needs. ValueError from a model without ``supports_range_scale``."""
        ...

    def set_range_scale(self, scale: float) -> None:
        """Use ``scale`` as lidar_scale_to_map_scale (an online estimate). ValueError from a model without
        ``supports_range_scale``."""
        ...


__all__ = ["Preparation", "RangeProbe", "SensorModel", "resolve_max_range", "sweep_offsets"]
