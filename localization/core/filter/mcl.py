"""Monte Carlo Localization: the particle filter itself (no ROS).

State: N particles (x, y, θ) in the map frame and their log-weights.

    predict:   p_i ← motion_model(p_i, u)                       on every odometry delta u
    correct:   log w_i ← log w_i + log p(z | p_i)              on every scan z
               normalise in log space (log-sum-exp)
    resample:  systematic (low-variance) resampling when ESS < fraction · N,
               then a small Gaussian roughening so the cloud never collapses to one state;
               with a KLD sampler (``kld.py``) each resampling also picks N (adaptive count)
    estimate:  weighted mean of x, y; circular mean of θ; weighted covariance (θ wrapped)

A tempered update (``sensor_update`` with ``stages`` > 1, the first scan after an initial pose) applies the same scan
in stages, as progressive correction (Musso, Oudjane & Le Gland) and tempered SMC do:

    stage k:   log w_i ← log w_i + β_k · log p(z | p_i),   β_k the largest step with ESS ≥ ess_target · N
               (bisection), Σ_k β_k = 1 (the last stage takes what is left)
    between:   resample, then jitter by N(0, h² Σ) (Σ the cloud's covariance, h = (4 / (N (d + 2)))^(1/(d+4)),
               d = 3: the regularised particle filter's Gaussian kernel bandwidth)

The scan counts once (the β sum to 1), but the particles move to where it points between stages:
a wide initial cloud (0.5 m, 0.2 rad) holds only a few particles inside one scan's posterior
(centimetres), and a plain update leaves the estimate on whichever of them the draw put nearest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.cost import WEIGH, CostMeter
from localization.core.draws import standard_normal_into
from localization.core.filter.kernels import estimate_kernel, weigh_kernel
from localization.core.filter.resampling import NO_NOISE, resample_kernel, systematic_indices
from localization.core.geometry import circular_mean, compose, wrap_angle
from localization.core.models.motion import MotionModel
from localization.core.models.sensor import SensorModel
from localization.core.occupancy_map import OccupancyMap

# numpy passes over the N particles (or weights) of each step, counted from the code (``core.cost``)
MOTION_PASSES = 2  # per odometry piece: the noise draw, the compiled move
COMPOSE_PASSES = 14  # geometry.compose of the cloud: cos, sin, the products and sums, the wrap
NORMALISE_PASSES = 6  # numpy: add, max, subtract, exp, sum, subtract (compiled, with the ESS's weights: 3)
COVARIANCE_PASSES = 15  # two dots, the circular mean (4), the difference, its wrap (6), the weighting, the product
ESTIMATE_PASSES = 5 + 2 + 4 + COVARIANCE_PASSES  # numpy: the weights (5), the mean x, y, θ, the covariance
COMPILED_PASSES = 3  # weigh_kernel, estimate_kernel: three passes each (filter/kernels.py)
TEMPERING_PASSES = 2 + 30 * 5  # a stage's β: the bisection's effective sample sizes
KLD_RESAMPLE_PASSES = 20  # the KLD sampler's draw and bins, the copy, the roughening


@dataclass
class Estimate:
    pose: np.ndarray  # (3,) x, y, θ
    covariance: np.ndarray  # (3, 3) over x, y, θ


@dataclass(frozen=True)
class Snapshot:
    """A cloud as it was (copies of its particles and log weights), for ``MonteCarloLocalizer.restore``."""

    particles: np.ndarray  # (N, 3)
    log_weights: np.ndarray  # (N,)

    def estimate(self) -> Estimate:
        """The estimate of this cloud (as ``MonteCarloLocalizer.estimate`` gives it once restored)."""
        return estimate_of(self.particles, self.log_weights)


class _Arrays:
    """The arrays a filter reuses from scan to scan, by name and shape (no allocation in steady state): a
    spare of a kind is one that is neither in ``busy`` (the filter's current arrays, a snapshot's)."""

    def __init__(self):
        self._pool: dict[tuple, list[np.ndarray]] = {}

    def spare(self, kind: str, shape: tuple, busy=()) -> np.ndarray:
        pool = self._pool.setdefault((kind, shape), [])
        taken = {id(a) for a in busy}
        for a in pool:
            if id(a) not in taken:
                return a
        if len(pool) > 4:  # shapes come and go (an adaptive count): keep the pool small
            pool.pop(0)
        pool.append(np.empty(shape))
        return pool[-1]


@dataclass
class SensorUpdateResult:
    ok: bool  # False when every particle had likelihood 0 (weights left unchanged)
    resampled: bool
    ess: float  # effective sample size after the update, before resampling
    mean_log_likelihood: float  # log of the weighted-mean likelihood


class MonteCarloLocalizer:
    def __init__(self, motion_model: MotionModel, sensor_model: SensorModel, num_particles: int = 2000,
                 resample_ess_fraction: float = 1.0, roughening=(0.01, 0.01, 0.005), rng=None, kld=None):
        if num_particles < 1:
            raise ValueError(f"num_particles must be >= 1, got {num_particles}")
        self.motion_model = motion_model
        self.sensor_model = sensor_model
        self.num_particles = int(num_particles)
        self.resample_ess_fraction = float(resample_ess_fraction)
        self.roughening = np.asarray(roughening, dtype=float).reshape(3)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.particles = np.zeros((self.num_particles, 3))
        self.log_weights = np.full(self.num_particles, -np.log(self.num_particles))
        self.initialized = False
        self.kld = kld  # a filter.kld.KLDSampler: each resampling picks the particle count (None: fixed)
        self.kld_hold = False  # True: keep the current count even with a KLD sampler (a global spread)
        self.beams_used: tuple[int | None, int] | None = None  # the last sensor update's (used, offered) beams
        self.cost = CostMeter()  # beams cast and passes over the cloud (``core.cost``; the localizer shares one)
        self._arrays = _Arrays()  # reused from scan to scan
        self._held: tuple = ()  # the arrays the last snapshot holds: not written until it is taken back
        self._weights = None  # (log weights, exp of them, Σ of their squares) of the last compiled weighing

    # ------------------------------------------------------------------ initialisation
    def initialize_gaussian(self, pose, covariance=None, std=(0.5, 0.5, 0.2)) -> None:
        """Particles drawn around ``pose`` from N(pose, covariance), or independent ``std``."""
        pose = np.asarray(pose, dtype=float).reshape(3)
        if covariance is not None:
            cov = np.asarray(covariance, dtype=float).reshape(3, 3)
            cov = 0.5 * (cov + cov.T)
            vals, vecs = np.linalg.eigh(cov)
            with np.errstate(over="ignore", invalid="ignore"):
                noise = (self.rng.standard_normal((self.num_particles, 3)) * np.sqrt(np.clip(vals, 0, None))) @ vecs.T
            if not np.all(np.isfinite(noise)):  # a covariance too large to sample: the plain spread
                covariance = None
        if covariance is None:
            noise = self.rng.standard_normal((self.num_particles, 3)) * np.asarray(std, dtype=float)
        self.particles = pose + noise
        self.particles[:, 2] = wrap_angle(self.particles[:, 2])
        self._reset_weights()

    def initialize_uniform(self, occupancy_map: OccupancyMap) -> None:
        """Global localization: particles uniform over the map's free cells, headings uniform."""
        self.particles = occupancy_map.sample_free_poses(self.num_particles, self.rng)
        self._reset_weights()

    def resize(self, num_particles: int) -> None:
        """Change the particle count. An initialised cloud is resampled (systematic, by weight) to
        the new count, so its distribution is kept; the next initialisation uses the new count."""
        n = int(num_particles)
        if n < 1:
            raise ValueError(f"num_particles must be >= 1, got {n}")
        if self.initialized and n != self.num_particles:
            self.particles = self.particles[systematic_indices(self.weights, n, self.rng.random())]
            self.log_weights = np.full(n, -np.log(n))
        self.num_particles = n

    def set_particles(self, poses) -> None:
        """Replace the cloud by ``poses`` (N, 3), equally weighted (e.g. seeds of a global start)."""
        self.particles = np.asarray(poses, dtype=float).reshape(-1, 3)
        self.num_particles = len(self.particles)
        self._reset_weights()

    def snapshot(self) -> Snapshot:
        """The particles and their log weights, for ``restore`` within the same scan: no copy, the filter
        writes its updates into other arrays (``_spare``) and moves the cloud in place only at the next scan."""
        self._held = (self.particles, self.log_weights)
        return Snapshot(self.particles, self.log_weights)

    def _spare(self, kind: str, shape: tuple) -> np.ndarray:
        """A reused array (``_Arrays``) that is not the current cloud's nor the last snapshot's."""
        return self._arrays.spare(kind, shape, (self.particles, self.log_weights, *self._held))

    def restore(self, snapshot: Snapshot) -> None:
        """Back to a ``snapshot`` (an update undone); the snapshot's arrays become the filter's."""
        self.particles, self.log_weights = snapshot.particles, snapshot.log_weights
        self.num_particles = len(self.particles)

    def forget(self) -> None:
        """The cloud no longer describes the robot (a new map with none of it in free space): not
        initialised until the next initialisation."""
        self.initialized = False

    def hold_count(self, hold: bool) -> None:
        """Keep the particle count even with a KLD sampler (True: a global spread), or let it adapt."""
        self.kld_hold = bool(hold)

    def _reset_weights(self) -> None:
        log_weights = self._spare("log_weights", (self.num_particles,))
        log_weights.fill(-np.log(self.num_particles))
        self.log_weights = log_weights
        self.initialized = True

    # ------------------------------------------------------------------ updates
    def motion_update(self, odometry, slip: float = 0.0, slip_var: float = 0.0) -> None:
        """Move every particle by the robot-frame odometry delta [dx, dy, dθ] (``slip``, ``slip_var``: the
        mean (m) and variance (m²) of how much farther forward the robot went; ``MotionModel.evaluate``)."""
        n = len(self.particles)
        self.motion_model.evaluate(self.particles, odometry, out=self.particles, slip=slip, slip_var=slip_var,
                                   noise_out=self._spare("noise", (n, 3)))
        self.cost.sweep("motion", MOTION_PASSES)

    def motion_updates(self, pieces, slips) -> None:
        """``motion_update`` of each odometry piece (P, 3) in turn with its slip (P, 2), in one compiled pass over
        the particles (``MotionModel.evaluate_pieces``: the same draws and arithmetic)."""
        n, count = len(self.particles), len(pieces)
        if count == 0:
            return
        noisy = count if not self.motion_model.deterministic else 0
        noise = self._spare("noise_pieces", (noisy, n, 3)) if noisy else None
        self.motion_model.evaluate_pieces(self.particles, pieces, slips, out=self.particles, noise_out=noise)
        self.cost.sweep("motion", count + 1)  # a draw per noisy piece, one compiled move

    def shift(self, delta) -> None:
        """Move every particle by the robot-frame delta exactly (no noise), e.g. back in time."""
        self.particles = compose(self.particles, np.asarray(delta, dtype=float).reshape(3))
        self.cost.sweep("shift", COMPOSE_PASSES)

    def sensor_update(self, ranges, angles, offsets=None, range_max=None, stages: int = 1,
                      ess_target: float = 0.5) -> SensorUpdateResult:
        """Weight particles by the scan, normalise, and resample when the ESS is low. ``offsets``:
        per-beam laser motion of a deskewed sweep (sensor models with ``supports_deskew``);
        ``range_max``: the scan's own (m), the sensor model's z_max unless ``laser_max_range`` > 0.
        ``stages`` > 1: tempered (module docstring): each stage weighs by the largest share β of the
        scan that keeps the ESS ≥ ``ess_target`` · N, then resamples and jitters; the last stage takes
        what is left. ``mean_log_likelihood``: the log of the weighted-mean likelihood (per beam,
        squashed; a health signal), for a tempered update the sum of its stages' (the scan's evidence,
        as one plain update gives it; the jitter leaves it slightly low)."""
        stages = max(1, int(stages))
        n_target = ess_target * self.num_particles
        left, evidence = 1.0, 0.0
        for stage in range(stages):
            log_lik = self._log_likelihood(ranges, angles, offsets, range_max, WEIGH if stage == 0 else "tempered")
            last = stage == stages - 1
            beta = left if last else self._stage_share(log_lik, left, n_target)
            step_ll = self._weigh(log_lik if beta == 1.0 else np.where(np.isfinite(log_lik), beta * log_lik, -np.inf))
            if step_ll is None:
                if stage == 0:
                    return SensorUpdateResult(False, False, 0.0, -np.inf)
                break  # the jitter moved every particle where the scan is impossible: the stages so far stand
            evidence += step_ll
            left -= beta
            if left <= 1e-9 or last:
                break
            self._resample_regularised(np.exp(self.log_weights))
        return self._resample_if_due(evidence)

    def _stage_share(self, log_lik, left: float, n_target: float) -> float:
        """A tempered stage's β (``_tempering_step``); ``left`` when no particle can explain the scan."""
        possible = np.isfinite(log_lik)
        if not possible.any():
            return left
        self.cost.sweep("tempered", TEMPERING_PASSES)
        return _tempering_step(self.log_weights, log_lik, possible, left, n_target)

    def _log_likelihood(self, ranges, angles, offsets, range_max, name: str = WEIGH) -> np.ndarray:
        """The sensor model's log p(z | particle); records the (used, offered) beams of the update and
        counts its N × B beams as ``name`` (the cost's ``weigh``, or an extra)."""
        extra = {"out": self._spare("likelihood", (len(self.particles),))} if getattr(
            self.sensor_model, "accepts_out", False) else {}  # a model that writes into a reused array
        log_lik = self.sensor_model.log_likelihood(self.particles, ranges, angles, offsets=offsets,
                                                   range_max=range_max, **extra)
        self.cost.cast(name, len(self.particles) * int(np.size(ranges)))
        self.cost.sweep(WEIGH)
        # (beams used, beams offered) by this update: beam skipping and out-of-range beams leave some out
        self.beams_used = (self.sensor_model.last_beams_used, int(np.size(ranges)))
        return log_lik

    def _weigh(self, log_factor) -> float | None:
        """log w ← log w + log_factor, normalised in log space; returns the log normaliser (log of the
        weighted-mean factor), or None with the weights unchanged when every particle gets weight 0.
        Compiled (``kernels.weigh_kernel``, into reused arrays) when numba is there; ``weigh_numpy`` else."""
        n = len(self.log_weights)
        if weigh_kernel is None or np.shape(log_factor) != (n,):
            self.cost.sweep("normalise", NORMALISE_PASSES)
            weighed = weigh_numpy(self.log_weights, log_factor)
            if weighed is None:
                return None
            self.log_weights, norm = weighed
            return norm
        self.cost.sweep("normalise", COMPILED_PASSES)  # with the weights and their squares (the ESS)
        out, weights = self._spare("log_weights", (n,)), self._spare("weights", (n,))
        norm, squares = weigh_kernel(self.log_weights, np.ascontiguousarray(log_factor, dtype=float), out, weights)
        if not math.isfinite(norm):
            return None
        self.log_weights, self._weights = out, (out, weights, squares)
        return float(norm)

    def _resample_if_due(self, mean_ll: float) -> SensorUpdateResult:
        """Resample when the ESS is below ``resample_ess_fraction`` · N (always at 1.0)."""
        if self._weights is not None and self._weights[0] is self.log_weights:  # the weighing's own
            _, weights, squares = self._weights
        else:
            weights = np.exp(self.log_weights)
            squares = float(np.dot(weights, weights))
            self.cost.sweep("ess", 2)  # exp, dot
        ess = float(1.0 / squares)
        resampled = ess < self.resample_ess_fraction * self.num_particles or self.resample_ess_fraction >= 1.0
        if resampled:
            self.resample(weights)
        return SensorUpdateResult(True, resampled, ess, mean_ll)

    def _resample_regularised(self, weights) -> None:
        """Systematic resampling, then the regularised kernel's jitter N(0, h² Σ) (Σ: the weighted
        covariance before resampling, θ wrapped; h the Gaussian kernel's optimal bandwidth for d = 3)."""
        n = self.num_particles
        cov = weighted_covariance(self.particles, weights)
        self.cost.sweep("tempered", COVARIANCE_PASSES + 12)  # the covariance, the draw and its jitter
        h = (4.0 / (n * 5.0)) ** (1.0 / 7.0)
        # a floor of the ordinary roughening keeps Σ positive definite when the cloud is degenerate
        chol = np.linalg.cholesky(cov + np.diag(np.maximum(self.roughening, 1e-6) ** 2))
        drawn = self.particles[systematic_indices(weights, n, self.rng.random())]
        drawn += h * self.rng.standard_normal((n, 3)) @ chol.T
        drawn[:, 2] = wrap_angle(drawn[:, 2])
        self.particles = drawn
        self._reset_weights()

    def resample(self, weights=None) -> None:
        """Systematic (low-variance) resampling, then roughening."""
        if weights is None:
            weights = self.weights
        if self.kld is not None and not self.kld_hold:  # adaptive count: KLD draws the indices and their number
            self.cost.sweep("resample", KLD_RESAMPLE_PASSES)
            draw = self.kld.resample(self.particles, weights, self.rng)
            self.num_particles = draw.indices.size
            self._take_roughened(self.particles[draw.indices])
            return
        n = self.num_particles
        if resample_kernel is not None and self.particles.shape == (n, 3) and len(weights) == n:
            # one compiled O(N) pass: the same draws, indices and arithmetic as the numpy code below
            u0 = self.rng.random()
            noise = NO_NOISE
            if self.roughening.any():
                noise = self._spare("noise", (n, 3))
                standard_normal_into(self.rng, noise)  # the same draws as standard_normal((n, 3))
            out = self._spare("particles", (n, 3))
            resample_kernel(self.particles, np.ascontiguousarray(weights, dtype=float), u0, noise,
                             self.roughening, out)
            self.cost.sweep("resample", 3)  # the noise draw, the compiled walk, the weights reset
            self.particles = out
            self._reset_weights()
            return
        self.cost.sweep("resample", 12)  # cumsum, searchsorted, the copy, the roughening, the weights reset
        self._take_roughened(self.particles[systematic_indices(weights, n, self.rng.random())])

    def _take_roughened(self, drawn: np.ndarray) -> None:
        """The drawn particles (a new array), roughened by N(0, roughening²) jitter, weights uniform."""
        if self.roughening.any():
            drawn += self.rng.standard_normal((len(drawn), 3)) * self.roughening
            drawn[:, 2] = wrap_angle(drawn[:, 2])
        self.particles = drawn
        self._reset_weights()

    # ------------------------------------------------------------------ estimate
    @property
    def weights(self) -> np.ndarray:
        return normalised_weights(self.log_weights)

    def estimate(self) -> Estimate:
        """Weighted mean x, y, circular mean θ, and the weighted covariance (θ wrapped)."""
        self.cost.sweep("estimate", COMPILED_PASSES if estimate_kernel is not None else ESTIMATE_PASSES)
        return estimate_of(self.particles, self.log_weights)


def normalised_weights(log_weights) -> np.ndarray:
    """exp(log_weights), normalised to sum to 1."""
    w = np.exp(log_weights - log_weights.max())
    return w / w.sum()


def weighted_covariance(particles, weights) -> np.ndarray:
    """The weighted covariance (3, 3) of particles (N, 3) about their weighted mean (θ: circular, wrapped)."""
    x = float(np.dot(weights, particles[:, 0]))
    y = float(np.dot(weights, particles[:, 1]))
    th = circular_mean(particles[:, 2], weights)
    diff = particles - np.array([x, y, th])
    diff[:, 2] = wrap_angle(diff[:, 2])
    return (diff * weights[:, None]).T @ diff


def weigh_numpy(log_weights, log_factor) -> tuple[np.ndarray, float] | None:
    """(log_weights + log_factor normalised in log space, the log normaliser); None when every particle gets
    weight 0: the numpy reference of ``kernels.weigh_kernel``."""
    combined = log_weights + log_factor
    peak = combined.max()
    if not np.isfinite(peak):
        return None
    norm = float(peak + np.log(np.exp(combined - peak).sum()))
    return combined - norm, norm


def estimate_of(particles, log_weights) -> Estimate:
    """Weighted mean x, y, circular mean θ, and the weighted covariance (θ wrapped) of a cloud: compiled
    (``kernels.estimate_kernel``) when numba is there, ``estimate_of_numpy`` else."""
    particles = np.asarray(particles, dtype=float)
    if estimate_kernel is None or particles.ndim != 2 or len(particles) == 0:
        return estimate_of_numpy(particles, log_weights)
    mean, cov = np.empty(3), np.empty((3, 3))
    estimate_kernel(np.ascontiguousarray(particles), np.ascontiguousarray(log_weights, dtype=float), mean, cov)
    return Estimate(mean, cov)


def estimate_of_numpy(particles, log_weights) -> Estimate:
    """``estimate_of`` in numpy: the reference of the compiled kernel."""
    w = normalised_weights(log_weights)
    x = float(np.dot(w, particles[:, 0]))
    y = float(np.dot(w, particles[:, 1]))
    th = circular_mean(particles[:, 2], w)
    return Estimate(np.array([x, y, th]), weighted_covariance(particles, w))


def effective_sample_size(log_weights) -> float:
    """1 / Σ w̃_i² of the normalised exp(log_weights) (0 when every weight is 0)."""
    peak = np.max(log_weights)
    if not np.isfinite(peak):
        return 0.0
    w = np.exp(log_weights - peak)
    return float(w.sum() ** 2 / np.dot(w, w))


def _tempering_step(log_weights, log_lik, possible, left: float, n_target: float, iterations: int = 30) -> float:
    """The largest β in (0, left] with ESS(log_weights + β · log_lik) ≥ n_target (bisection on β; the
    impossible particles drop out at any β > 0); ``left`` when even that keeps the ESS."""
    base = np.where(possible, log_weights, -np.inf)
    ll = np.where(possible, log_lik, 0.0)
    if effective_sample_size(base + left * ll) >= n_target:
        return left
    lo, hi = 0.0, left
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if effective_sample_size(base + mid * ll) >= n_target:
            lo = mid
        else:
            hi = mid
    return max(lo, left * 1e-6)
