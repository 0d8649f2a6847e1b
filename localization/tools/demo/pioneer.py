"""The Pioneer bags' figures (docs/replay.md, "A second robot and building"): convergence against the
yardstick, jumps once converged, recoveries, agreement where the yardstick is confident, the share of
scans the localizer said disagree with the map."""
from __future__ import annotations

import numpy as np

CONVERGED_M = 0.5  # m: converged once the estimate stays this close to the yardstick's confident poses ...
CONVERGED_HOLD_S = 5.0  # s: ... for this long
EARLY_REFERENCE_S = 10.0  # s: the yardstick must be confident this soon after the start to time convergence
END_WINDOW_S = 10.0  # s: the end of a bag, for its end agreement
HEALTHY_AGREEMENT = 0.8  # else: converged at the first scan whose agreement reaches this


class StatusCounter:
    """``on_scan`` hook: counts the scans after which ``Localizer.status`` says the scans disagree with the map."""

    def __init__(self):
        self.scans = 0
        self.holding = 0

    def __call__(self, scan, localizer) -> None:
        from localization.core.localizer.recovery import HOLDING
        self.scans += 1
        self.holding += int(localizer.status == HOLDING)


def converge_time(t, err, threshold: float, t_start: float, hold: float = CONVERGED_HOLD_S):
    """Seconds from ``t_start`` to the first time t_i from which ``err`` stays ≤ ``threshold`` for
    ``hold`` seconds, or to the end of the series if that comes sooner (None: never; NaN errors are
    not scored)."""
    t, err = np.asarray(t, dtype=float), np.asarray(err, dtype=float)
    ok = np.isfinite(err)
    t, err = t[ok], err[ok]
    if t.size == 0:
        return None
    bad = err > threshold
    # next_bad[i]: time of the first bad sample at or after i (inf: none)
    bad_t = np.where(bad, t, np.inf)
    next_bad = np.minimum.accumulate(bad_t[::-1])[::-1]
    good = ~bad & ((next_bad - t >= hold) | ~np.isfinite(next_bad))
    if not good.any():
        return None
    return float(max(t[np.argmax(good)] - t_start, 0.0))


def pioneer_metrics(res, holding: StatusCounter | None = None) -> dict:
    """Convergence, jumps, recoveries, agreement where the yardstick is confident, lost share."""
    from localization.eval import metrics as M
    p = res.options.params
    t0 = res.init_t if res.init_t is not None else (float(res.scan_t[0]) if len(res.scan_t) else 0.0)
    out = {"max_jump_m": M.max_jump(res.est_poses), "recoveries": int(res.counts.get("recoveries", 0)),
           "refused_jumps": int(res.counts.get("refused_jumps", 0))}
    if len(res.agreement_t):  # where the bag ends: do the scans fit the map there (the yardstick may not know)?
        end = np.asarray(res.agreement_t) >= res.agreement_t[-1] - END_WINDOW_S
        out["end_agreement_median"] = float(np.nanmedian(np.asarray(res.agreement)[end]))
    ref = res.reference
    conv, how, conf_agree = None, None, None
    if ref is not None and ref.good.any() and len(res.scan_t) >= 2:
        rt, rp = ref.good_track()
        order = np.argsort(res.scan_t, kind="stable")
        est = M.interpolate_poses(rt, res.scan_t[order], res.scan_poses[order])
        err = np.hypot(est[:, 0] - rp[:, 0], est[:, 1] - rp[:, 1])
        if rt[0] - t0 <= EARLY_REFERENCE_S:
            conv, how = converge_time(rt, err, CONVERGED_M, t0), "yardstick"
        if len(res.agreement_t):
            idx = np.clip(np.searchsorted(res.agreement_t, rt), 0, len(res.agreement_t) - 1)
            near = np.abs(res.agreement_t[idx] - rt) < 1e-6
            conf_agree = float(np.median(res.agreement[idx[near]])) if near.any() else None
        out["confident_scans"] = int(ref.good.sum())
        out["error_vs_yardstick_median_m"] = float(np.nanmedian(err)) if np.isfinite(err).any() else None
        out["off_share"] = out["last_off_s"] = out["false_recoveries"] = None
        if conv is not None:  # once converged: where the estimate is off (how much, until when) and far off
            since = rt >= t0 + conv
            far = np.flatnonzero(since & (err > CONVERGED_M))
            out["off_share"] = float(far.size / max(np.count_nonzero(since & np.isfinite(err)), 1))
            out["last_off_s"] = float(rt[far[-1]] - t0) if far.size else None
            out["false_recoveries"] = M.false_recoveries(rt[since], err[since], M.FALSE_RECOVERY_M, 0.0)
    if how is None:
        hit = np.flatnonzero(np.asarray(res.agreement) >= HEALTHY_AGREEMENT)
        conv = float(res.agreement_t[hit[0]] - t0) if hit.size else None
        how = f"agreement >= {HEALTHY_AGREEMENT}"
    out.update(time_to_converge_s=conv, converge_by=how, confident_agreement_median=conf_agree)
    # jumps once converged (a global start's first estimates are the mean of a spread cloud: not jumps)
    after = res.est_t >= t0 + conv if conv is not None else np.zeros(len(res.est_t), dtype=bool)
    out["max_jump_after_converge_m"] = M.max_jump(res.est_poses[after]) if conv is not None else None
    h = np.asarray(res.health, dtype=float)
    h = h[np.isfinite(h)]
    out["health_lost_share"] = float(np.mean(h < p.health_lost_floor)) if h.size else None
    out["holding_share"] = (holding.holding / holding.scans) if holding is not None and holding.scans else None
    return out


