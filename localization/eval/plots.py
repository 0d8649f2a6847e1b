"""Plots of a localization run (matplotlib, Agg backend: files only, no display needed).

Figures are drawn on their own Agg canvas (``new_figure``: no pyplot, no figure registry to close)
with margins fixed in inches (``fixed_margins``) instead of ``tight_layout``, which draws every
figure once more only to measure it."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from localization.core.occupancy_map import OccupancyMap


def _pyplot():
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    return plt


def new_figure(rows: int = 1, figsize=(10.0, 6.0), sharex: bool = False):
    """A figure on its own Agg canvas and its ``rows`` axes (one column), as an array."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(rows, 1, sharex=sharex, squeeze=False)[:, 0]


def fixed_margins(fig, left: float = 0.85, right: float = 0.2, bottom: float = 0.55, top: float = 0.4,
                  between: float = 0.3) -> None:
    """Subplot margins in inches (room for tick labels, axis labels and a title; ``between``: the
    gap between stacked axes)."""
    w, h = fig.get_size_inches()
    rows = max(len(fig.axes), 1)
    axes_h = max((h - top - bottom - between * (rows - 1)) / rows, 0.1)
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        hspace=between / axes_h)


def save(fig, path) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path


def map_image(occupancy_map: OccupancyMap, xlim, ylim, resolution: float | None = None) -> np.ndarray:
    """The map resampled onto a world-aligned raster over ``xlim`` x ``ylim`` (rows from the
    bottom): 0 occupied, 1 free, 0.75 unknown / off the map. Exact for any origin yaw."""
    res = resolution or occupancy_map.resolution
    xs = np.arange(xlim[0], xlim[1], res) + 0.5 * res
    ys = np.arange(ylim[0], ylim[1], res) + 0.5 * res
    gx, gy = np.meshgrid(xs, ys)
    cr = occupancy_map.world_to_grid(np.stack([gx, gy], axis=-1))
    inside = occupancy_map.in_bounds(cr)
    img = np.full(gx.shape, 0.75)
    data = occupancy_map.data[cr[..., 1][inside], cr[..., 0][inside]]
    img[inside] = np.where(data >= 50, 0.0, np.where(data >= 0, 1.0, 0.75))
    return img


def plot_trajectory(path, occupancy_map: OccupancyMap, est_poses, truth_poses=None, initial_pose=None,
                    title: str = "", margin: float = 3.0, reference_poses=None) -> Path:
    """Map, ground truth (if any), the reference track of scan matches (if any: ``reference_poses``,
    its good matches) and the estimated trajectory; the view fits them all plus ``margin``."""
    est = np.asarray(est_poses, dtype=float).reshape(-1, 3)
    truth = None if truth_poses is None or not len(truth_poses) else np.asarray(truth_poses, dtype=float).reshape(-1, 3)
    ref = None if reference_poses is None or not len(reference_poses) else \
        np.asarray(reference_poses, dtype=float).reshape(-1, 3)
    pts = [p[:, :2] for p in (est, truth, ref) if p is not None]
    allp = np.vstack(pts) if sum(len(p) for p in pts) else np.zeros((1, 2))
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    if not len(allp):
        allp = np.zeros((1, 2))
    lo, hi = allp.min(axis=0) - margin, allp.max(axis=0) + margin
    span = hi - lo
    res = max(occupancy_map.resolution, float(span.max()) / 2000.0)
    img = map_image(occupancy_map, (lo[0], hi[0]), (lo[1], hi[1]), res)
    aspect = span[1] / max(span[0], 1e-6)
    w = 10.0
    fig, (ax,) = new_figure(1, (w, float(np.clip(w * aspect, 4.0, 14.0))))
    ax.imshow(img, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap="gray", vmin=0, vmax=1,
              interpolation="nearest")
    if truth is not None:
        ax.plot(truth[:, 0], truth[:, 1], "-", color="tab:green", lw=2.0, label="ground truth", zorder=3)
        ax.plot(truth[0, 0], truth[0, 1], "o", color="tab:green", ms=7, zorder=3)
    if ref is not None:
        ax.plot(ref[:, 0], ref[:, 1], ".", color="tab:cyan", ms=4.0, label="reference track (scan matches)",
                zorder=3)
    if len(est):
        ax.plot(est[:, 0], est[:, 1], "-", color="tab:red", lw=1.0, label="estimate", zorder=4)
    if initial_pose is not None:  # an outline under the tracks: the start of the track stays visible
        x, y, th = initial_pose
        ax.arrow(x, y, 0.8 * np.cos(th), 0.8 * np.sin(th), width=0.05, facecolor="none", edgecolor="tab:blue",
                 lw=1.2, alpha=0.8, zorder=2, label="initial pose")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.legend(loc="best", fontsize=8)
    fixed_margins(fig)
    return save(fig, path)


def plot_errors(path, t0: float, ct_t=None, ct_error=None, heading_error=None, agreement_t=None, agreement=None,
                title: str = "", threshold: float = 0.2, particles_t=None, particles=None, track=None) -> Path:
    """One panel each, against time since ``t0``, for what is given:

    - position error |x̂ − x| against the ground truth (``ct_t``, ``ct_error``, metres) with the
      convergence ``threshold`` line;
    - along-track and cross-track error against the truth (``track``: an object with ``t``,
      ``along``, ``cross``, e.g. ``localization.eval.reference.TrackErrors``; signed metres,
      along > 0 ahead of the car, cross > 0 left of its path);
    - heading error |θ̂ − θ| (``heading_error``, radians, drawn in degrees) on its own axis;
    - scan–map agreement; the particle count when it changes (adaptive_particles, global spreads)."""
    has_truth = ct_t is not None and len(ct_t) > 0
    has_track = has_truth and track is not None and len(track.t) > 0
    has_heading = has_truth and heading_error is not None and len(heading_error) > 0
    has_agree = agreement_t is not None and len(agreement_t) > 0
    has_count = particles is not None and len(particles) > 0 and np.ptp(particles) > 0
    rows = int(has_truth) + int(has_track) + int(has_heading) + int(has_agree) + int(has_count) or 1
    fig, axes = new_figure(rows, (10, 2.6 * rows + 0.6), sharex=True)
    panels = iter(axes)
    if has_truth:
        ax = next(panels)
        t = np.asarray(ct_t) - t0
        ax.plot(t, ct_error, color="tab:red", lw=1.0, label="position error |x̂ − x|")
        ax.axhline(threshold, color="gray", ls="--", lw=0.8, label=f"{threshold} m (converged)")
        ax.set_ylabel("position error (m)")
        err = np.asarray(ct_error, dtype=float)
        top = np.nanmax(err[np.isfinite(err)]) if np.isfinite(err).any() else threshold
        ax.set_ylim(0, 1.1 * max(top, 1.25 * threshold))  # the whole trace, and the threshold line below the top
        ax.legend(loc="upper right", fontsize=8)
    if has_track:
        ax = next(panels)
        tt = np.asarray(track.t) - t0
        ax.plot(tt, track.along, color="tab:orange", lw=1.0, label="along-track (> 0 ahead)")
        ax.plot(tt, track.cross, color="tab:blue", lw=1.0, label="cross-track (> 0 left)")
        ax.axhline(0.0, color="gray", lw=0.6)
        ax.set_ylabel("along / cross (m)")
        ax.legend(loc="upper right", fontsize=8)
    if has_heading:
        ax = next(panels)
        ax.plot(np.asarray(ct_t) - t0, np.degrees(np.abs(heading_error)), color="tab:purple", lw=0.8,
                label="heading error |θ̂ − θ|")
        ax.set_ylabel("heading error (deg)")
        ax.set_ylim(bottom=0)
        ax.legend(loc="upper right", fontsize=8)
    if has_agree:
        ax = next(panels)
        ax.plot(np.asarray(agreement_t) - t0, agreement, color="tab:gray", lw=1.0, label="scan-map agreement")
        ax.set_ylabel("scan-map agreement")
        ax.set_ylim(0, 1.02)
    if has_count:
        ax = next(panels)
        ax.step(np.asarray(particles_t) - t0, particles, where="post", color="tab:green", lw=1.0)
        ax.set_ylabel("particles")
        ax.set_yscale("log")
    if not (has_truth or has_agree):
        axes[0].text(0.5, 0.5, "no data", ha="center", va="center", transform=axes[0].transAxes)
    axes[0].set_title(title)
    axes[-1].set_xlabel("time since start (s)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fixed_margins(fig)
    return save(fig, path)
