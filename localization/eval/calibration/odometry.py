"""Odometry timing, scales and laser mount from pairs of scan-to-map matches, with the odometry's slips
and skids left out (``localization.eval.calibration``, steps 3–4)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose, integrate_twists, inverse, relative, wrap_angle
from localization.eval.calibration.result import CalibrationError
from localization.eval.reference import odometry_inputs

PAIR_SPACING_S = 0.4
SIGMA_XY = 0.01  # m: residual scale of a relative laser translation
SIGMA_THETA = 0.005  # rad
SLIP_MAD_FACTOR = 4.0  # a pair slips when its speed or yaw-rate disagreement exceeds this many robust σ ...
SLIP_SPEED_FRACTION = 0.1  # ... and this fraction of the robot's 95th-percentile speed (yaw rate)
SLIP_ROUNDS = 3


# --------------------------------------------------------------------------------------------
# Dead reckoning with the speed and the yaw rate on their own clocks
# --------------------------------------------------------------------------------------------


def dead_reckon_channels(odom_t, twist, query_t, a=1.0, b=1.0, c=0.0, delta_v=0.0, delta_w=0.0) -> np.ndarray:
    """Odometry poses (…, 3) at ``query_t`` (scan clock, 0 at the first breakpoint): the speed
    message k held over (t_{k−1} + δ_v, t_k + δ_v], the yaw rate over (t_{k−1} + δ_ω, t_k + δ_ω]
    (corrected: a·(vx, vy), b·ωz + c); between the union of both sets of breakpoints both are
    constant, so each piece is one exact arc (``integrate_twists``), composed in closed form.
    The last twists are extrapolated, the first run backwards before the first breakpoint.
    With δ_v = δ_ω = δ this is ``reference.dead_reckon(odom_t, twist, query_t − δ)``."""
    t, tw, q = odometry_inputs(odom_t, twist, query_t)
    M = len(t)
    if M < 2:
        return np.zeros(q.shape + (3,))
    tv, tr = t + delta_v, t + delta_w
    br = np.unique(np.concatenate([tv, tr]))
    mid = 0.5 * (br[:-1] + br[1:])

    def held(stamps, x):  # the message whose period holds x (the first / last beyond the ends)
        return np.clip(np.searchsorted(stamps, x, side="left"), 1, M - 1)

    kv, kw = held(tv, mid), held(tr, mid)
    steps = integrate_twists(a * tw[kv, 0], a * tw[kv, 1], b * tw[kw, 2] + c, np.diff(br))
    th = np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    cs, sn = np.cos(th[:-1]), np.sin(th[:-1])
    chain = np.zeros((len(br), 3))
    chain[1:, 0] = np.cumsum(cs * steps[:, 0] - sn * steps[:, 1])
    chain[1:, 1] = np.cumsum(sn * steps[:, 0] + cs * steps[:, 1])
    chain[:, 2] = wrap_angle(th)
    j = np.clip(np.searchsorted(br, q, side="left"), 1, len(br) - 1)  # the piece (br_{j-1}, br_j] holding q
    dt = q - br[j - 1]  # < 0 only before the first breakpoint
    qv, qw = kv[j - 1], kw[j - 1]
    return compose(chain[j - 1], integrate_twists(a * tw[qv, 0], a * tw[qv, 1], b * tw[qw, 2] + c, dt))


# --------------------------------------------------------------------------------------------
# Estimation
# --------------------------------------------------------------------------------------------


def _pairs(t, spacing):
    """Index pairs (i, j) with t_j − t_i the first step ≥ spacing (at most 1.5 spacing)."""
    t = np.asarray(t, dtype=float)
    j = np.searchsorted(t, t + spacing, side="left")
    ok = j < len(t)
    i = np.flatnonzero(ok)
    j = j[ok]
    keep = t[j] - t[i] <= 1.5 * spacing
    return i[keep], j[keep]


@dataclass
class _PairFit:
    x: np.ndarray  # (8,) δ_v, δ_ω, a, b, c, m_x, m_y, m_ψ
    sigma: np.ndarray
    residual: np.ndarray  # (P, 3) in m, m, rad
    cost: float


def _fit_pairs(lt, lp, odom_t, twist, i0, i1, p0, split: bool) -> _PairFit:
    """Robust least squares over the pairs (package doc, step 4); ``split``: δ_v and δ_ω apart."""
    from scipy.optimize import least_squares
    obs = relative(lp[i0], lp[i1])
    scale = np.array([SIGMA_XY, SIGMA_XY, SIGMA_THETA])

    def unpack(p):
        return (p[0], p[1], *p[2:]) if split else (p[0], p[0], *p[1:])

    def residuals(p):
        dv, dw, a, b, c, mx, my, myaw = unpack(p)
        B = dead_reckon_channels(odom_t, twist, np.concatenate([lt[i0], lt[i1]]), a, b, c, dv, dw)
        n = len(i0)
        m = np.array([mx, my, myaw])
        pred = compose(compose(inverse(m), relative(B[:n], B[n:])), m)
        r = obs - pred
        r[:, 2] = wrap_angle(r[:, 2])
        return (r / scale).ravel()

    x0 = np.asarray(p0, dtype=float) if split else np.delete(np.asarray(p0, dtype=float), 1)
    lo = np.array([-0.5, -0.5, 0.5, 0.5, -1.0, -2.0, -2.0, -math.pi])
    hi = np.array([0.5, 0.5, 2.0, 2.0, 1.0, 2.0, 2.0, math.pi])
    if not split:
        lo, hi = np.delete(lo, 1), np.delete(hi, 1)
    sol = least_squares(residuals, np.clip(x0, lo + 1e-9, hi - 1e-9), bounds=(lo, hi), loss="soft_l1", f_scale=2.0,
                        x_scale=np.full(len(x0), 0.01), diff_step=np.r_[[1e-4] * (2 if split else 1),
                                                                         [1e-5] * 6])
    r = residuals(sol.x).reshape(-1, 3) * scale
    J = sol.jac
    n, k = J.shape
    s2 = 2.0 * sol.cost / max(n - k, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.inf)
    period = float(np.median(np.diff(lt))) if len(lt) > 1 else PAIR_SPACING_S
    overlap = max(1.0, PAIR_SPACING_S / max(period, 1e-3))
    sig = np.sqrt(np.clip(np.diag(cov), 0, None) * overlap)
    x = sol.x if split else np.insert(sol.x, 1, sol.x[0])
    sig = sig if split else np.insert(sig, 1, sig[0])
    return _PairFit(x=x, sigma=sig, residual=r, cost=float(sol.cost))


def slip_mask(lt, lp, odom_t, twist, i0, i1, fit: np.ndarray) -> tuple[np.ndarray, dict]:
    """Pairs (bool, True = kept) whose scan-matched forward speed and yaw rate agree with the
    odometry's under ``fit`` (package doc, step 3), and the bounds used. The speed is compared at
    the odometry's own stamps (δ_v = 0): a skid (wheels locked while the robot slides) is a
    disagreement a time offset must not be allowed to explain away."""
    dv, dw, a, b, c, mx, my, myaw = fit
    B = dead_reckon_channels(odom_t, twist, np.concatenate([lt[i0], lt[i1]]), a, b, c, 0.0, dw)
    n = len(i0)
    m = np.array([mx, my, myaw])
    pred = compose(compose(inverse(m), relative(B[:n], B[n:])), m)
    obs = relative(lp[i0], lp[i1])
    dt = lt[i1] - lt[i0]
    e_v = (obs[:, 0] - pred[:, 0]) / dt
    e_w = wrap_angle(obs[:, 2] - pred[:, 2]) / dt
    speed = np.hypot(obs[:, 0], obs[:, 1]) / dt
    rate = np.abs(obs[:, 2]) / dt

    def bound(e, level):
        mad = 1.4826 * float(np.median(np.abs(e - np.median(e))))
        return max(SLIP_MAD_FACTOR * mad, SLIP_SPEED_FRACTION * float(np.percentile(level, 95)), 1e-6)

    bv, bw = bound(e_v, speed), bound(e_w, rate)
    keep = (np.abs(e_v) <= bv) & (np.abs(e_w) <= bw)
    return keep, {"speed_bound_mps": bv, "yaw_rate_bound_radps": bw}


def fit_odometry(laser_t, laser_poses, odom_t, twist, mount0=(0.275, 0.0, 0.0), spacing: float = PAIR_SPACING_S,
                 start=(0.0, 1.0), log=None):
    """(δ, a, b, c, m_x, m_y, m_ψ), their σ, the pairs used, residual rms, the rejected pairs (dict)
    and the per-channel offsets (package doc, steps 3–4). ``start``: (δ, a) to begin from."""
    say = log or (lambda *_: None)
    lt = np.asarray(laser_t, dtype=float)
    lp = np.asarray(laser_poses, dtype=float)
    ot = np.asarray(odom_t, dtype=float)
    t_rel = ot[0]
    ot, lt = ot - t_rel, lt - t_rel
    i0, i1 = _pairs(lt, spacing)
    if len(i0) < 20:
        raise CalibrationError(f"only {len(i0)} pairs of matched scans {spacing} s apart: too few to calibrate")
    p = np.array([start[0], start[0], start[1], 1.0, 0.0, *mount0], dtype=float)
    keep = np.ones(len(i0), dtype=bool)
    bounds: dict = {}
    fit = None
    for _ in range(SLIP_ROUNDS):
        if keep.sum() < 20:
            raise CalibrationError(f"only {int(keep.sum())} of {len(i0)} scan pairs agree with the odometry: too few")
        fit = _fit_pairs(lt, lp, ot, twist, i0[keep], i1[keep], p, split=False)
        p = fit.x
        new_keep, bounds = slip_mask(lt, lp, ot, twist, i0, i1, p)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    fit = _fit_pairs(lt, lp, ot, twist, i0[keep], i1[keep], p, split=False)
    split = _fit_pairs(lt, lp, ot, twist, i0[keep], i1[keep], fit.x, split=True)
    intervals = _union(lt[i0[~keep]], lt[i1[~keep]])
    covered = float(sum(e - s for s, e in intervals))
    rejected = {"pairs": int((~keep).sum()), "of": int(len(i0)), "share": float((~keep).mean()),
                "seconds": covered, "intervals_s": [[s - lt[0], e - lt[0]] for s, e in intervals], **bounds}
    say(f"slip/skid: {rejected['pairs']} of {len(i0)} scan pairs rejected ({100 * rejected['share']:.1f} %, "
        f"{covered:.1f} s of the bag; bounds {bounds['speed_bound_mps']:.3f} m/s, "
        f"{bounds['yaw_rate_bound_radps']:.3f} rad/s)")
    r = fit.residual
    rms = {"xy_m": float(np.sqrt(np.mean(r[:, :2] ** 2))), "theta_rad": float(np.sqrt(np.mean(r[:, 2] ** 2)))}
    values = np.delete(fit.x, 1)
    sigmas = np.delete(fit.sigma, 1)
    channels = {"speed_s": float(split.x[0]), "speed_sigma_s": float(split.sigma[0]),
                "yaw_rate_s": float(split.x[1]), "yaw_rate_sigma_s": float(split.sigma[1])}
    return values, sigmas, int(keep.sum()), rms, rejected, channels


def _union(starts, ends) -> list:
    """The union of the intervals [starts_i, ends_i] as sorted, disjoint [start, end] pairs."""
    out: list = []
    for s, e in sorted(zip(np.asarray(starts, dtype=float), np.asarray(ends, dtype=float))):
        if out and s <= out[-1][1]:
            out[-1][1] = max(out[-1][1], e)
        else:
            out.append([float(s), float(e)])
    return out
