"""The yardstick's plot: along- and cross-track error against time, and the reference's own σ."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from localization.eval.reference.errors import track_errors

if TYPE_CHECKING:
    from localization.eval.reference.result import ReferenceTrack


def plot_reference(path, ref: ReferenceTrack, est_t, est_poses, t0: float = 0.0, title: str = ""):
    """Along- and cross-track error vs time (scored scans), scans whose match leaves an axis free
    marked; the reference's own σ along and across the track."""
    from localization.eval.plots import fixed_margins, new_figure, save
    rt, rp = ref.good_track()
    err = track_errors(est_t, est_poses, rt, rp)
    fig, axes = new_figure(2, (10, 6), sharex=True)
    ax = axes[0]
    ax.plot(err.t - t0, err.along, color="tab:red", lw=1.0, label="along-track (> 0 ahead)")
    ax.plot(err.t - t0, err.cross, color="tab:blue", lw=1.0, label="cross-track (> 0 left)")
    ax.axhline(0.0, color="gray", lw=0.6)
    amb_t = ref.t[ref.ambiguous] - t0
    if amb_t.size:
        ax.plot(amb_t, np.zeros_like(amb_t), "|", color="tab:orange", ms=10, label="match leaves an axis free")
    ax.set_ylabel("error vs reference (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title)
    ax = axes[1]
    ax.plot(err.t - t0, err.position, color="black", lw=1.0, label="position error")
    ax.plot(ref.t - t0, ref.std_along, color="tab:green", lw=0.8, alpha=0.8, label="reference σ along track")
    ax.plot(ref.t - t0, ref.std_cross, color="tab:purple", lw=0.8, alpha=0.8, label="reference σ across track")
    ax.set_ylabel("m")
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time since start (s)")
    for a in axes:
        a.grid(True, alpha=0.3)
    fixed_margins(fig)
    return save(fig, path)
