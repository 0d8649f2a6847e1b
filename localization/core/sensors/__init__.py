"""Sensor models: how likely a scan is from each particle's pose.

Every model follows one small protocol (``SensorModel`` below, as nav2_amcl's ``sensors/laser``
siblings and Beluga's sensor models do), so the filter, health checks, replay and benchmarks
treat them alike:

    model.set_map(occupancy_map)                     # (re)build what the model precomputes
    model.log_likelihood(particles, ranges, angles)  # (N,) squashed log weights, -inf = impossible

``beam.BeamModel``: the course's beam model (p_hit, p_short, p_max, p_rand) over ray-cast
expected ranges, tabulated 201 × 201.
``likelihood_field.LikelihoodFieldModel``: nav2_amcl's likelihood field (each beam's end point
scored by its distance to the nearest occupied cell; no ray casting); ``sensor_model`` picks one
(``localizer.build_filter``), docs/models.md compares them.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np


class SensorModel(Protocol):
    """What the filter needs of a sensor model."""

    laser_offset: np.ndarray  # (3,) laser pose in base_link

    @property
    def max_range(self) -> float: ...

    def set_map(self, occupancy_map) -> None: ...

    def log_likelihood(self, particles, ranges, angles=None) -> np.ndarray: ...
