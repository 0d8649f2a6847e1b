"""Odometry motion model.

Each particle moves by the odometry delta expressed in the robot frame at k-1, with noise
added in the robot frame (never the world frame — the lesson of the reference lab report):

    p_k = p_{k-1} ⊕ (u + ε),    u = [dx, dy, dθ],    ε ~ N(0, diag(σx², σy², σθ²))

i.e. ``[x, y] += R(θ) [dx + εx, dy + εy]`` and ``θ += dθ + εθ``. The noise grows with the
size of the motion, plus a small floor while moving:

    σx = a_trans·|t| + a_rot_to_trans·|dθ| + floor_xy        t = hypot(dx, dy)
    σy = a_lateral·|t| + floor_xy
    σθ = a_rot·|dθ| + a_trans_to_rot·|t| + floor_theta

A car standing still (``|t| < still_trans`` and ``|dθ| < still_rot``) gets no noise at all, so
a parked car's cloud does not diffuse. ``deterministic=True`` adds no noise: exact composition.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from localization.core.geometry import wrap_angle
from localization.core.parameters import default

try:  # a compiled single pass when numba is there (pinned); the numpy code below otherwise
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None


STILL_TRANS = 1e-4  # m: below this and STILL_ROT the car is standing still (no noise)
STILL_ROT = 1e-4  # rad


@dataclass(frozen=True)
class MotionNoiseParams:
    """Noise of the motion model (see the module docstring); the parameter table's
    ``motion_<name>`` entries, defaults the course's (``course=True``)."""

    a_trans: float = default("motion_a_trans", course=True)  # m of x noise per m travelled
    a_lateral: float = default("motion_a_lateral", course=True)  # m of y noise per m travelled
    a_rot: float = default("motion_a_rot", course=True)  # rad of θ noise per rad turned
    a_rot_to_trans: float = default("motion_a_rot_to_trans", course=True)  # m of x noise per rad turned
    a_trans_to_rot: float = default("motion_a_trans_to_rot", course=True)  # rad of θ noise per m travelled
    floor_xy: float = default("motion_floor_xy", course=True)  # m per update while moving
    floor_theta: float = default("motion_floor_theta", course=True)  # rad per update while moving
    still_trans: float = STILL_TRANS
    still_rot: float = STILL_ROT

    @classmethod
    def from_parameters(cls, params) -> "MotionNoiseParams":
        """From a ``Parameters`` mapping (``motion_a_trans`` -> ``a_trans``, ...)."""
        return cls(**{f.name: params["motion_" + f.name] for f in fields(cls) if "motion_" + f.name in params})


class MotionModel:
    DEFAULT_NOISE = asdict(MotionNoiseParams())

    def __init__(self, deterministic: bool = False, rng=None, params: MotionNoiseParams | None = None, **noise):
        unknown = set(noise) - set(self.DEFAULT_NOISE)
        if unknown:
            raise TypeError(f"unknown motion noise parameter(s): {sorted(unknown)}")
        self.deterministic = bool(deterministic)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        base = asdict(params) if params is not None else self.DEFAULT_NOISE
        for name, default_value in base.items():
            value = float(noise.get(name, default_value))
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"motion noise {name} must be a finite number >= 0, got {value}")
            setattr(self, name, value)

    def noise_sigmas(self, odometry) -> np.ndarray:
        """Standard deviations (σx, σy, σθ) of the robot-frame noise for one odometry delta."""
        dx, dy, dth = (float(v) for v in odometry)
        trans, rot = np.hypot(dx, dy), abs(dth)
        if trans < self.still_trans and rot < self.still_rot:
            return np.zeros(3)
        return np.array([
            self.a_trans * trans + self.a_rot_to_trans * rot + self.floor_xy,
            self.a_lateral * trans + self.floor_xy,
            self.a_rot * rot + self.a_trans_to_rot * trans + self.floor_theta,
        ])

    def evaluate(self, particles, odometry, out=None) -> np.ndarray:
        """Move particles (N, 3) by odometry [dx, dy, dθ] (robot frame); returns (N, 3).

        ``out`` may be ``particles`` itself to update in place."""
        particles = np.asarray(particles, dtype=float)
        odometry = np.asarray(odometry, dtype=float).reshape(3)
        n = particles.shape[0]
        noise = None
        if not self.deterministic:
            sig = self.noise_sigmas(odometry)
            if sig.any():
                noise = self.rng.standard_normal((n, 3))
        if _move_kernel is not None and particles.ndim == 2 and particles.shape[1] == 3:
            # one compiled pass: same arithmetic as below, no (N, 3) temporaries (10k particles: ~0.3 ms)
            if out is None:
                out = np.empty_like(particles)
            _move_kernel(particles, odometry, noise if noise is not None else _NO_NOISE,
                         sig if noise is not None else odometry, out)
            return out
        if noise is None:
            delta = np.broadcast_to(odometry, (n, 3))
        else:
            delta = odometry + noise * sig
        c = np.cos(particles[:, 2])
        s = np.sin(particles[:, 2])
        if out is None:
            out = np.empty_like(particles)
        x = particles[:, 0] + c * delta[:, 0] - s * delta[:, 1]
        y = particles[:, 1] + s * delta[:, 0] + c * delta[:, 1]
        out[:, 2] = wrap_angle(particles[:, 2] + delta[:, 2])
        out[:, 0] = x
        out[:, 1] = y
        return out


_NO_NOISE = np.zeros((0, 3))

if njit is not None:
    @njit(cache=True, nogil=True)
    def _move_kernel(particles, odometry, noise, sig, out):  # pragma: no cover - compiled
        """out[i] = particles[i] ⊕ (odometry + noise[i] * sig), θ wrapped to (-π, π]; ``noise``
        of length 0 means none. ``out`` may be ``particles``."""
        noisy = noise.shape[0] == particles.shape[0]
        two_pi = 2.0 * np.pi
        for i in range(particles.shape[0]):
            d0 = odometry[0]
            d1 = odometry[1]
            d2 = odometry[2]
            if noisy:
                d0 = odometry[0] + noise[i, 0] * sig[0]
                d1 = odometry[1] + noise[i, 1] * sig[1]
                d2 = odometry[2] + noise[i, 2] * sig[2]
            th = particles[i, 2]
            c = math.cos(th)
            s = math.sin(th)
            x = particles[i, 0] + c * d0 - s * d1
            y = particles[i, 1] + s * d0 + c * d1
            w = (th + d2 + np.pi) % two_pi - np.pi  # as geometry.wrap_angle
            if w <= -np.pi:
                w += two_pi
            out[i, 0] = x
            out[i, 1] = y
            out[i, 2] = w
else:  # pragma: no cover
    _move_kernel = None
