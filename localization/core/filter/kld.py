"""KLD-adaptive sample size (Fox 2003, "Adapting the sample size in particle filters through
KLD-sampling"; nav2_amcl's ``pf_resample_limit``).

Draw particles until their number n reaches the bound that keeps, with probability 1 − δ, the
Kullback–Leibler divergence between the sampled and the true (binned) posterior below ε. With
k the number of histogram bins (``kld_bin_xy`` m × ``kld_bin_xy`` m × ``kld_bin_theta`` rad)
that the particles drawn so far occupy, and z = ``pf_z`` (the upper standard normal quantile
z_{1−δ}, used as the value itself, as nav2's ``pf_z``), ε = ``pf_err``:

    n(k) = (k − 1) / (2ε) · (1 − 2/(9(k − 1)) + sqrt(2/(9(k − 1))) · z)³

clipped to [``min_particles``, ``max_particles``]; k ≤ 1 gives ``min_particles`` (Fox's bound is
0 there; nav2 returns ``max_samples`` instead, which keeps a one-bin cloud at the maximum).

Sampling, vectorised (no Python loop over particles): draw indices by systematic resampling
and shuffle them (so every prefix is a fair sample of the weighted cloud), bin each drawn
particle, mark the first occurrence of each bin in the drawn order (``np.unique(...,
return_index=True)``), so k(t) = number of bins among the first t draws is a cumulative sum;
the sample size is the first t with t ≥ n(k(t)) (nav2 stops at the first t > n(k)), or
``max_particles``. The draws come in doubling chunks (min_particles, then as many again, ...,
each its own shuffled systematic sample), so a tight cloud costs ~min_particles draws.
A tight cloud occupies few bins: n falls to ``min_particles``; a spread one, many: n grows up to ``max_particles``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from localization.core.filter.resampling import systematic_indices
from localization.core.parameters import default

_BITS = 21  # bits per bin coordinate in the packed key (±2^20 bins of 0.5 m: ±500 km)
_MASK = (1 << _BITS) - 1


@dataclass(frozen=True)
class KLDParams:
    """The KLD sampler's parameters; names and meanings as in the parameter table."""

    min_particles: int = default("min_particles")
    max_particles: int = default("max_particles")
    pf_err: float = default("pf_err")  # ε
    pf_z: float = default("pf_z")  # z_(1-δ)
    kld_bin_xy: float = default("kld_bin_xy")  # m
    kld_bin_theta: float = default("kld_bin_theta")  # rad

    @classmethod
    def from_parameters(cls, params) -> "KLDParams":
        return cls(**{f.name: params[f.name] for f in fields(cls)})


def kld_sample_size(k, pf_err: float, pf_z: float, min_particles: int, max_particles: int):
    """n(k) of the module docstring (scalar or array of bin counts k), clipped to [min, max]."""
    k = np.asarray(k, dtype=float)
    km1 = np.maximum(k - 1.0, 1.0)  # k <= 1 is replaced below
    b = 2.0 / (9.0 * km1)
    n = np.ceil(km1 / (2.0 * pf_err) * (1.0 - b + np.sqrt(b) * pf_z) ** 3)
    n = np.where(k <= 1.0, min_particles, n)
    n = np.clip(n, min_particles, max_particles).astype(np.int64)
    return int(n) if n.ndim == 0 else n


def bin_keys(particles, bin_xy: float, bin_theta: float) -> np.ndarray:
    """(N,) int64: one key per histogram bin (x, y, θ) of each particle; θ wrapped to [−π, π)."""
    p = np.asarray(particles, dtype=float)
    ix = np.floor(p[:, 0] / bin_xy).astype(np.int64) & _MASK
    iy = np.floor(p[:, 1] / bin_xy).astype(np.int64) & _MASK
    theta = np.mod(p[:, 2] + np.pi, 2.0 * np.pi) - np.pi
    it = np.floor(theta / bin_theta).astype(np.int64) & _MASK
    return (ix << (2 * _BITS)) | (iy << _BITS) | it


def count_bins(particles, bin_xy: float, bin_theta: float) -> int:
    """k: the number of occupied histogram bins."""
    return int(np.unique(bin_keys(particles, bin_xy, bin_theta)).size)


@dataclass
class KLDResult:
    indices: np.ndarray  # (n,) indices into the cloud, in draw order
    bins: int  # k: occupied bins among the drawn particles


class KLDSampler:
    """``KLDSampler(KLDParams(...))``; ``sample_size(k)``; ``resample(particles, weights, rng)``
    → the indices of a KLD-sized, weight-proportional resample of the cloud."""

    def __init__(self, params: KLDParams | None = None, **overrides):
        from dataclasses import replace
        self.params = p = replace(params or KLDParams(), **overrides)
        if not 1 <= p.min_particles <= p.max_particles:
            raise ValueError(f"need 1 <= min_particles ({p.min_particles}) <= max_particles ({p.max_particles})")
        if not (0 < p.pf_err < 1 and p.pf_z > 0 and p.kld_bin_xy > 0 and p.kld_bin_theta > 0):
            raise ValueError("pf_err must be in (0, 1); pf_z, kld_bin_xy, kld_bin_theta > 0")

    @classmethod
    def from_parameters(cls, params) -> "KLDSampler":
        return cls(KLDParams.from_parameters(params))

    def sample_size(self, k):
        p = self.params
        return kld_sample_size(k, p.pf_err, p.pf_z, p.min_particles, p.max_particles)

    def resample(self, particles, weights, rng: np.random.Generator) -> KLDResult:
        """Shuffled systematic draws, cut at the first t with t ≥ n(k(t)) (or max_particles).

        Drawn in chunks that double (min_particles, then as many again, ...), each chunk a shuffled
        systematic sample of its own, so a tight cloud costs ~min_particles draws, not max."""
        p = self.params
        m = p.max_particles
        drawn = np.zeros(0, dtype=np.intp)
        chunk = min(m, p.min_particles)
        while True:
            part = systematic_indices(weights, chunk, rng.random())
            drawn = np.concatenate([drawn, part[rng.permutation(chunk)]])
            keys = bin_keys(particles[drawn], p.kld_bin_xy, p.kld_bin_theta)
            _, first = np.unique(keys, return_index=True)
            new_bin = np.zeros(drawn.size, dtype=np.int64)
            new_bin[first] = 1
            k = np.cumsum(new_bin)  # bins among the first t draws, t = 1..len(drawn)
            done = np.arange(1, drawn.size + 1) >= self.sample_size(k)
            if done.any():
                n = int(np.argmax(done)) + 1
                return KLDResult(drawn[:n], int(k[n - 1]))
            if drawn.size >= m:
                return KLDResult(drawn[:m], int(k[m - 1]))
            chunk = min(m - drawn.size, drawn.size)
