"""A runtime parameter change (``core.runtime_parameters.Change``) applied to the localizer's parts.

    prepare_change   the slow part, on any thread, touching nothing in use: the filter's kernels for the
                     new parameters compiled into numba's cache, and with a range-table change the sensor
                     model's map structure built (or loaded) by a beam model with the new parameters
    apply_change     under the Localizer's lock, between two updates: the shared parameters take the new
                     values (what the parts read where they use them), the filter its particle count
                     (an initialised cloud resampled by weight; a global spread keeps its count until it
                     converges), the motion model its noise, the beam model its parameters (its
                     likelihood tables rebuilt) and the prepared range table
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from localization.core.compile_cache import ensure_compiled
from localization.core.models.beam import BeamModel, BeamModelParams
from localization.core.models.motion import MotionNoiseParams
from localization.core.runtime_parameters import Change, How

_BEAM_FIELDS = {f.name for f in fields(BeamModelParams)}


@dataclass(frozen=True)
class Prepared:
    """A sensor model's map structure made for a change: ``prepared`` (from ``prepare``) for ``occupancy_map``."""

    occupancy_map: object
    prepared: object


def prepare_change(change: Change, occupancy_map, log=None) -> Prepared | None:
    """The slow part of ``change`` (module docstring); None when it has nothing to prepare."""
    if not change.needs_preparation:
        return None
    ensure_compiled(change.params, log)
    if How.TABLE not in change.hows or occupancy_map is None:
        return None
    model = BeamModel(BeamModelParams.from_parameters(change.params))
    return Prepared(occupancy_map, model.prepare(occupancy_map))


def apply_change(change: Change, shared, pf, model, occupancy_map, prepared: Prepared | None = None) -> None:
    """``change`` into ``shared`` (the Parameters every part reads), ``pf`` (the filter) and ``model`` (the
    sensor model); the caller holds the Localizer's lock."""
    new, hows = change.params, change.hows
    dict.update(shared, {name: new[name] for name in change.changed})
    if How.FILTER in hows:
        if pf.kld is None and not pf.kld_hold:  # a global spread keeps its count until it converges
            pf.resize(new.num_particles)
        pf.resample_ess_fraction = float(new.resample_ess_fraction)
        pf.roughening = np.array([new.roughening_xy, new.roughening_xy, new.roughening_theta], dtype=float)
    if How.MOTION in hows:
        noise = asdict(MotionNoiseParams.from_parameters(new))
        noise.pop("robot_model_type")
        for name, value in noise.items():
            setattr(pf.motion_model, name, float(value))
    if How.SENSOR in hows or How.TABLE in hows:
        model.params = replace(model.params, **{name: new[name] for name in change.changed if name in _BEAM_FIELDS})
        model.precompute_sensor_model()
        if How.TABLE in hows and occupancy_map is not None:
            fresh = prepared is not None and prepared.occupancy_map is occupancy_map
            model.set_map(occupancy_map, prepared.prepared if fresh else None)  # a newer map: prepared here
