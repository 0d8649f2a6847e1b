"""Odometry motion model: a random walk in the distance travelled and the angle turned.

Each particle moves by the odometry piece u = [dx, dy, dθ] (a constant-twist arc, in the robot frame
at the piece's start) plus noise, composed in the robot frame (never the world frame — the lesson of
the reference lab report):

    p_k = p_{k-1} ⊕ (u + ε),    ε ~ N(0, Σ(u))

i.e. ``[x, y] += R(θ) [dx + εx, dy + εy]`` and ``θ += dθ + εθ``.

Noise (rate-free). While the robot drives, noise enters continuously, its variance growing linearly
with the motion (a random walk in arc length s and angle turned r). Over a piece, in the noise frame
(along / across the robot's heading; an omni base: along / across its direction of travel)::

    q_along  = a_trans²·s       + a_rot_to_trans²·r + floor_xy²·(s + r)        [m²]
    q_across = a_lateral²·s     + a_rot_to_trans²·r + floor_xy²·(s + r)        [m²]
    q_θ      = a_trans_to_rot²·s + a_rot²·r         + floor_theta²·(s + r)     [rad²]

    s = arc length of the piece (m),  r = |dθ| (rad)

Units: a_trans, a_lateral in m/√m; a_rot in rad/√rad; a_rot_to_trans in m/√rad; a_trans_to_rot in
rad/√m; floor_xy in m/√(m + rad) and floor_theta in rad/√(m + rad) (a metre travelled and a radian
turned count alike). Σ(u) is the covariance this continuous walk builds up over the piece, to first
order: noise entering at fraction τ of the piece moves the end pose through

    Σ(u) = ∫₀¹ Φ(τ) Q Φ(τ)ᵀ dτ,    Q = diag(q_along, q_across, q_θ)
    Φ(τ) = [[R(θ(τ) + β), J (p(1) − p(τ))],      J = [[0, −1], [1, 0]]
            [0,           1              ]]

where p(τ), θ(τ) follow the piece's arc from p(0) = 0 and β is the noise frame's angle (0, or for an
omni base the bearing of travel): heading noise picked up on the way turns the rest of the piece.
On a straight piece of length s this is Var y = q_y s + q_θ s³/3, Cov(y, θ) = q_θ s²/2 (exactly what
many short pieces compose to), so the same motion split into 1 or 10 pieces spreads the particles
alike: values tuned on 50 Hz odometry hold at 20 Hz and with a 10 Hz lidar. The integral is taken
with 4-point Gauss–Legendre (exact for straight pieces).

Robot models (``ROBOT_MODELS``, parameter ``robot_model_type``): ``ackermann`` (default; a car, noise
in its own axes, the odometry's sideways motion kept), ``differential`` (turns on the spot; a reported
sideways velocity vy is impossible and is dropped, with one warning), ``omni`` (moves sideways; noise
along and across its direction of travel, so sideways motion brings sideways along-travel noise).

A robot standing still (``s < still_trans`` and ``r < still_rot``: 0.1 mm and 0.1 mrad per piece)
gets no noise at all, so a parked robot's cloud does not diffuse with odometry jitter.
``deterministic=True`` adds no noise: exact composition.

nav2_amcl's ``alpha1..alpha5`` (``nav2_alphas_to_noise``): nav2 draws its noise once per filter
update with variance α·Δ² (Δ the motion since the last update); updates come every
``update_min_d`` = 0.25 m or ``update_min_a`` = 0.2 rad (nav2's defaults), so over a long motion D its
variance grows by α·d·D: the same random walk with a² = α·d (d = 0.25 m or 0.2 rad).
"""
from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from localization.core.draws import standard_normal_into
from localization.core.geometry import integrate_twists, wrap_angle
from localization.core.models.motion_kernels import covariance_kernel as _covariance_kernel
from localization.core.models.motion_kernels import factor_kernel as _factor_kernel
from localization.core.models.motion_kernels import move_kernel as _move_kernel
from localization.core.models.motion_kernels import plan_move_kernel as _plan_move_kernel
from localization.core.parameters import ROBOT_MODEL_TYPES, default

LOG = logging.getLogger("localization.motion")

STILL_TRANS = 1e-4  # m per piece: below this and STILL_ROT the robot is standing still (no noise)
STILL_ROT = 1e-4  # rad per piece
NAV2_UPDATE_MIN_D = 0.25  # m: nav2_amcl's default update_min_d (its noise is drawn once per update)
NAV2_UPDATE_MIN_A = 0.2  # rad: nav2_amcl's default update_min_a

# 4-point Gauss–Legendre on [0, 1]: nodes and weights
_GL_X, _GL_W = np.polynomial.legendre.leggauss(4)
_GL_TAU, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


# ============================================================================================
# Robot models
# ============================================================================================


@dataclass(frozen=True)
class RobotModel:
    """What a base's kinematics change in the motion model."""

    name: str
    keeps_sideways: bool  # False: the odometry's sideways motion (vy) is dropped (it cannot move sideways)
    travel_frame: bool  # True: noise along/across the direction of travel; False: along/across the heading
    nav2_alpha2_draws: int  # how often nav2's model draws rotation-from-translation noise per update
    nav2_alpha5: bool  # nav2's alpha5 (strafe from translation) applies


ROBOT_MODELS = {m.name: m for m in (
    RobotModel("ackermann", keeps_sideways=True, travel_frame=False, nav2_alpha2_draws=2, nav2_alpha5=False),
    RobotModel("differential", keeps_sideways=False, travel_frame=False, nav2_alpha2_draws=2, nav2_alpha5=False),
    RobotModel("omni", keeps_sideways=True, travel_frame=True, nav2_alpha2_draws=1, nav2_alpha5=True),
)}


def robot_model(name: str) -> RobotModel:
    """The robot model of a ``robot_model_type`` value (our names or nav2's)."""
    try:
        return ROBOT_MODELS[ROBOT_MODEL_TYPES[name]]
    except (KeyError, TypeError):
        raise ValueError(f"robot_model_type {name!r} is not one of {', '.join(ROBOT_MODEL_TYPES)}") from None


# ============================================================================================
# Parameters
# ============================================================================================


@dataclass(frozen=True)
class MotionNoiseParams:
    """Noise of the motion model (see the module docstring); the parameter table's
    ``motion_<name>`` entries and ``robot_model_type``, defaults the course's (``course=True``)."""

    robot_model_type: str = default("robot_model_type", course=True)
    a_trans: float = default("motion_a_trans", course=True)  # m/√m: along-track noise per metre travelled
    a_lateral: float = default("motion_a_lateral", course=True)  # m/√m: across-track noise per metre travelled
    a_rot: float = default("motion_a_rot", course=True)  # rad/√rad: heading noise per radian turned
    a_rot_to_trans: float = default("motion_a_rot_to_trans", course=True)  # m/√rad: position noise per radian
    a_trans_to_rot: float = default("motion_a_trans_to_rot", course=True)  # rad/√m: heading noise per metre
    floor_xy: float = default("motion_floor_xy", course=True)  # m/√(m + rad): position noise per motion
    floor_theta: float = default("motion_floor_theta", course=True)  # rad/√(m + rad): heading noise per motion
    still_trans: float = STILL_TRANS
    still_rot: float = STILL_ROT

    @classmethod
    def from_parameters(cls, params, log: logging.Logger | None = None) -> "MotionNoiseParams":
        """From a ``Parameters`` mapping (``motion_a_trans`` -> ``a_trans``, ...); nav2's ``alpha1..5``,
        where set (>= 0), replace the values they map to (``nav2_alphas_to_noise``, one log line)."""
        values = {f.name: params["motion_" + f.name] for f in fields(cls) if "motion_" + f.name in params}
        noise = cls(robot_model_type=params.get("robot_model_type", "ackermann"), **values)
        alphas = {i: params.get(f"alpha{i}", -1.0) for i in range(1, 6)}
        alphas = {i: float(a) for i, a in alphas.items() if a is not None and a >= 0}
        return nav2_alphas_to_noise(noise, alphas, log) if alphas else noise


def nav2_alphas_to_noise(noise: MotionNoiseParams, alphas: dict, log: logging.Logger | None = None
                         ) -> MotionNoiseParams:
    """``noise`` with nav2_amcl's alphas {1..5: α} converted (module docstring, a² = α·d)::

        alpha1 rot from rot      -> a_rot          = √(α1 · 0.2 rad)
        alpha2 rot from trans    -> a_trans_to_rot = √(k · α2 · 0.25 m)   k = 2 ackermann/differential, 1 omni
        alpha3 trans from trans  -> a_trans        = √(α3 · 0.25 m)
        alpha4 trans from rot    -> a_rot_to_trans = √(α4 · 0.2 rad)
        alpha5 strafe from trans -> a_lateral      = √(α5 · 0.25 m)       omni only (nav2 ignores it otherwise)

    nav2's differential model draws its rotation noise twice per update (before and after the
    translation), hence k = 2. It has no floor: motion_floor_* keep their values. One info line
    says what each given alpha became."""
    robot = robot_model(noise.robot_model_type)
    d, a = NAV2_UPDATE_MIN_D, NAV2_UPDATE_MIN_A
    rules = {1: ("a_rot", a), 2: ("a_trans_to_rot", robot.nav2_alpha2_draws * d), 3: ("a_trans", d),
             4: ("a_rot_to_trans", a), 5: ("a_lateral", d)}
    changes, said = {}, []
    for i in sorted(alphas):
        if i == 5 and not robot.nav2_alpha5:
            said.append(f"alpha5={alphas[i]:g} ignored (omni only)")
            continue
        name, scale = rules[i]
        changes[name] = math.sqrt(alphas[i] * scale)
        said.append(f"alpha{i}={alphas[i]:g} -> motion_{name}={changes[name]:.4g}")
    (log or LOG).info("nav2 alphas (robot_model_type %s, a^2 = alpha x nav2's update spacing 0.25 m / 0.2 rad): %s",
                      robot.name, ", ".join(said))
    return replace(noise, **changes)


# ============================================================================================
# The model
# ============================================================================================


class MotionModel:
    DEFAULT_NOISE = asdict(MotionNoiseParams())

    def __init__(self, deterministic: bool = False, rng=None, params: MotionNoiseParams | None = None, **noise):
        unknown = set(noise) - set(self.DEFAULT_NOISE)
        if unknown:
            raise TypeError(f"unknown motion noise parameter(s): {sorted(unknown)}")
        self.deterministic = bool(deterministic)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        base = asdict(params) if params is not None else dict(self.DEFAULT_NOISE)
        base.update(noise)
        self.robot_model_type = base.pop("robot_model_type")
        self.robot = robot_model(self.robot_model_type)
        for name, value in base.items():
            value = float(value)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"motion noise {name} must be a finite number >= 0, got {value}")
            setattr(self, name, value)
        self._warned_sideways = False

    # ------------------------------------------------------------------ the piece
    def _piece(self, u0: float, u1: float, w: float) -> tuple[float, float, float, float, float, float]:
        """(dx, dy, dθ, vx, vy, ω) of the piece [u0, u1, ω]: the piece as the robot model allows it (a differential
        base's sideways motion dropped) and the constant twist (per unit time) that drives it, from
        ``[dx, dy] = sinc(dθ/2) R(dθ/2) [vx, vy]``, ``dθ = ω``."""
        half = 0.5 * w
        k = max(math.sin(half) / half, 1e-3) if abs(half) > 1e-9 else 1.0  # chord / arc length
        c, s = math.cos(half), math.sin(half)
        vx, vy = (c * u0 + s * u1) / k, (-s * u0 + c * u1) / k
        if not self.robot.keeps_sideways and vy != 0.0:
            if not self._warned_sideways and abs(vy) > 1e-9:
                LOG.warning("robot_model_type %s: the odometry reports sideways motion (vy %.3g m per piece); a "
                            "differential base cannot move sideways: vy is ignored (forced to 0)",
                            self.robot.name, vy)
                self._warned_sideways = True
            vy = 0.0
            u0, u1 = k * c * vx, k * s * vx
        return u0, u1, w, vx, vy, w

    def _noise_terms(self, vx: float, vy: float, w: float) -> tuple[float, float, float, float] | None:
        """(β, q_along, q_across, q_θ) of the module docstring for the twist's piece; None: standing (no noise)."""
        s, r = math.hypot(vx, vy), abs(w)  # arc length (m), angle turned (rad)
        if s < self.still_trans and r < self.still_rot:
            return None
        amount = s + r
        qa = self.a_trans ** 2 * s + self.a_rot_to_trans ** 2 * r + self.floor_xy ** 2 * amount
        qc = self.a_lateral ** 2 * s + self.a_rot_to_trans ** 2 * r + self.floor_xy ** 2 * amount
        qt = self.a_trans_to_rot ** 2 * s + self.a_rot ** 2 * r + self.floor_theta ** 2 * amount
        beta = math.atan2(vy, vx) if self.robot.travel_frame and s >= self.still_trans else 0.0
        return beta, qa, qc, qt

    def _covariance(self, vx: float, vy: float, w: float) -> np.ndarray:
        terms = self._noise_terms(vx, vy, w)
        if terms is None:
            return np.zeros((3, 3))
        if _covariance_kernel is not None:  # the same integral, compiled (the numpy below is its reference)
            return _covariance_kernel(vx, vy, w, *terms, _GL_TAU, _GL_W)
        return covariance_reference(vx, vy, w, *terms)

    def noise_covariance(self, odometry) -> np.ndarray:
        """Σ(u) (3, 3): covariance of the robot-frame noise ε for one odometry piece [dx, dy, dθ]."""
        *_, vx, vy, w = self._piece(*np.asarray(odometry, dtype=float).reshape(3).tolist())
        return self._covariance(vx, vy, w)

    def noise_sigmas(self, odometry) -> np.ndarray:
        """Standard deviations (σx, σy, σθ) of the robot-frame noise for one odometry piece."""
        return np.sqrt(np.diag(self.noise_covariance(odometry)))

    # ------------------------------------------------------------------ moving particles
    def evaluate(self, particles, odometry, out=None, slip: float = 0.0, slip_var: float = 0.0,
                 noise_out=None) -> np.ndarray:
        """Move particles (N, 3) by odometry [dx, dy, dθ] (robot frame); returns (N, 3).

        ``slip`` (m) and ``slip_var`` (m²): the mean and variance of how much farther forward (along the
        heading at the piece's start) the robot went than the odometry says, a skid or wheel spin
        (``odometry.OdometryBuffer``): added to dx and to Σ(u)'s along-track variance. ``deterministic``
        ignores them. ``out`` may be ``particles`` itself to update in place; ``noise_out`` (N, 3): an array
        to draw the noise into (the same draws; None: a new one)."""
        particles = np.asarray(particles, dtype=float)
        u, factor = self._plan(odometry, slip, slip_var)
        n = particles.shape[0]
        noise = _NO_NOISE
        if factor is None:
            factor = _NO_FACTOR
        elif noise_out is not None and noise_out.shape == (n, 3):
            noise = standard_normal_into(self.rng, noise_out)  # the draws of standard_normal((n, 3))
        else:
            noise = standard_normal_into(self.rng, np.empty((n, 3)))
        if out is None:
            out = np.empty_like(particles)
        if _move_kernel is not None and particles.ndim == 2 and particles.shape[1] == 3:
            # one compiled pass: same arithmetic as move_reference, no (N, 3) temporaries
            _move_kernel(particles, u, noise, factor, out)
        else:
            move_reference(particles, u, noise, factor, out)
        return out

    def _plan(self, odometry, slip: float = 0.0, slip_var: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
        """(u, F): a piece's motion as the robot model allows it (with the slip's mean) and its noise factor
        (F Fᵀ = Σ(u) with the slip's variance; None: no noise, deterministic or standing): ``_plan_row`` finished
        in numpy, the reference of ``_plan_move_kernel``'s finish."""
        u0, u1, u2, vx, vy, w, *_, noisy, _, slipping, slip_var = self._plan_row(
            *np.asarray(odometry, dtype=float).reshape(3).tolist(), slip, slip_var)
        u = np.array([u0, u1, u2])
        if not noisy:
            return u, None
        cov = self._covariance(vx, vy, w)
        if slipping:  # a skid (or spin) along the robot's heading at the piece's start
            cov = cov + np.diag([slip_var, 0.0, 0.0])
        return u, (noise_factor(cov) if cov.any() else None)

    def evaluate_pieces(self, particles, pieces, slips, out=None, noise_out=None) -> np.ndarray:
        """``evaluate`` of each piece (P, 3) in turn with its slip (P, 2: mean, variance), in one compiled call
        (``_plan_move_kernel``: each piece's noise factor, the noisy pieces' draws in order, one pass over the
        particles): the same draws and the same arithmetic as P calls of ``evaluate``. ``noise_out``: an array
        (P, N, 3) or larger to draw into."""
        particles = np.asarray(particles, dtype=float)
        pieces = np.asarray(pieces, dtype=float).reshape(-1, 3)
        slips = np.asarray(slips, dtype=float).reshape(-1, 2)
        n = particles.shape[0]
        if out is None:
            out = np.empty_like(particles)
        if (_plan_move_kernel is None or particles.shape != (n, 3)
                or not isinstance(self.rng.bit_generator, np.random.PCG64)):  # the reference: piece by piece
            out[...] = particles
            for d, (s, v) in zip(pieces, slips):
                self.evaluate(out, d, out=out, slip=s, slip_var=v)
            return out
        rows = np.array([self._plan_row(*d, *s) for d, s in zip(pieces.tolist(), slips.tolist())]).reshape(-1, 14)
        room = 0 if self.deterministic else len(rows)  # at most one (N, 3) draw per piece; none when deterministic
        fits = noise_out is not None and noise_out.shape[0] >= room and noise_out.shape[1:] == (n, 3)
        _plan_move_kernel(self.rng, particles, rows, _GL_TAU, _GL_W, noise_out if fits else np.empty((room, n, 3)),
                          out)
        return out

    def _plan_row(self, d0: float, d1: float, d2: float, slip: float, slip_var: float) -> tuple:
        """A piece's plan up to its noise terms, in Python floats (``_plan`` and ``_plan_move_kernel`` finish it):
        (dx, dy, dθ (the slip's mean added), vx, vy, ω, β, q_along, q_across, q_θ, noisy at all (not
        deterministic), moving (not standing), slipping, the slip's variance (≥ 0))."""
        u0, u1, u2, vx, vy, w = self._piece(d0, d1, d2)
        if self.deterministic:
            return u0, u1, u2, vx, vy, w, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        terms = self._noise_terms(vx, vy, w)
        slipping = bool(slip or slip_var)  # a skid (or spin) along the robot's heading at the piece's start
        if slipping:
            u0 += slip
        return (u0, u1, u2, vx, vy, w, *(terms or (0.0, 0.0, 0.0, 0.0)), 1.0, float(terms is not None),
                float(slipping), max(slip_var, 0.0))


def noise_factor(cov) -> np.ndarray:
    """F (3, 3) with F Fᵀ = ``cov``: its eigenvectors scaled by the square roots of its eigenvalues (negative
    rounding clipped); compiled (``_factor_kernel``, numba's eigh is numpy's LAPACK routine: the same bits)."""
    if _factor_kernel is not None:
        return _factor_kernel(np.ascontiguousarray(cov, dtype=float))
    return noise_factor_numpy(cov)


def noise_factor_numpy(cov) -> np.ndarray:
    """``noise_factor`` in numpy: the reference of the compiled kernel."""
    vals, vecs = np.linalg.eigh(cov)
    return vecs * np.sqrt(np.clip(vals, 0.0, None))


def covariance_reference(vx: float, vy: float, w: float, beta: float, qa: float, qc: float, qt: float) -> np.ndarray:
    """Σ(u) of the module docstring by 4-point Gauss–Legendre, in numpy (the kernel's reference)."""
    arc = integrate_twists(vx, vy, w, np.append(_GL_TAU, 1.0))  # p(τ) at the nodes, then p(1)
    ang = w * _GL_TAU + beta
    phi = np.zeros((_GL_TAU.size, 3, 3))
    phi[:, 0, 0] = phi[:, 1, 1] = np.cos(ang)
    phi[:, 1, 0] = np.sin(ang)
    phi[:, 0, 1] = -phi[:, 1, 0]
    phi[:, 0, 2] = -(arc[-1, 1] - arc[:-1, 1])
    phi[:, 1, 2] = arc[-1, 0] - arc[:-1, 0]
    phi[:, 2, 2] = 1.0
    cov = np.einsum("n,nij,j,nkj->ik", _GL_W, phi, np.array([qa, qc, qt]), phi)
    return 0.5 * (cov + cov.T)


_NO_NOISE = np.zeros((0, 3))
_NO_FACTOR = np.zeros((3, 3))


def move_reference(particles, odometry, noise, factor, out) -> np.ndarray:
    """The numpy reference of the kernel: out = particles ⊕ (odometry + factor · noise_i), θ wrapped to
    (-π, π]; ``noise`` of length 0 means none. ``out`` may be ``particles``."""
    if noise.shape[0] == particles.shape[0]:
        delta = odometry + noise @ factor.T
    else:
        delta = np.broadcast_to(odometry, particles.shape)
    c = np.cos(particles[:, 2])
    s = np.sin(particles[:, 2])
    x = particles[:, 0] + c * delta[:, 0] - s * delta[:, 1]
    y = particles[:, 1] + s * delta[:, 0] + c * delta[:, 1]
    out[:, 2] = wrap_angle(particles[:, 2] + delta[:, 2])
    out[:, 0] = x
    out[:, 1] = y
    return out
