"""The replay's figures (localization.eval.plots, matplotlib Agg): what each axis is labelled, which
traces the legends name, and that a replay draws the reference track it computed."""
from __future__ import annotations

import numpy as np
import pytest
from helpers import corridor_map

from localization.eval import plots
from localization.eval.reference import TrackErrors


@pytest.fixture()
def figures(monkeypatch):
    """Every figure saved while the test runs (the real savefig still writes the file)."""
    import matplotlib.figure
    figs = []
    original = matplotlib.figure.Figure.savefig

    def savefig(fig, *a, **k):
        figs.append(fig)
        return original(fig, *a, **k)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    return figs


def _legend(ax) -> list[str]:
    leg = ax.get_legend()
    return [] if leg is None else [t.get_text() for t in leg.get_texts()]


def test_error_figure_labels_each_error_honestly(tmp_path, figures):
    t = np.linspace(0, 10, 200)
    pos = 0.05 + 0.02 * np.sin(t)
    heading = np.full_like(t, np.radians(30.0))  # 30 deg: on a metre axis it would cross the 0.2 m line
    track = TrackErrors(t=t, position=pos, along=0.03 * np.cos(t), cross=-0.02 * np.sin(t), heading=heading,
                        speed=np.ones_like(t))
    path = plots.plot_errors(tmp_path / "error.png", 0.0, t, pos, heading, t, np.full_like(t, 0.9), track=track)
    assert path.stat().st_size > 1000
    axes = figures[-1].axes
    assert len(axes) == 4  # position, along/cross, heading, agreement: one axis each, no twins
    assert len({a.get_position().bounds for a in axes}) == 4
    pos_ax, track_ax, head_ax, agree_ax = axes
    assert pos_ax.get_ylabel() == "position error (m)"
    assert any(label.startswith("position error") for label in _legend(pos_ax))
    assert not any("cross" in label or "heading" in label for label in _legend(pos_ax))
    assert pos_ax.get_ylim()[1] > 0.2 * 1.2  # the convergence line is inside the axis, not its top edge
    labels = _legend(track_ax)
    assert any(label.startswith("along-track") for label in labels)
    assert any(label.startswith("cross-track") for label in labels)
    assert np.nanmin(track_ax.lines[1].get_ydata()) < 0  # signed: the cross-track trace goes below zero
    assert head_ax.get_ylabel() == "heading error (deg)"
    assert np.allclose(head_ax.lines[0].get_ydata(), 30.0)
    assert not any(np.allclose(line.get_ydata(), 0.2) for line in head_ax.lines)  # no metre line on it
    assert agree_ax.get_ylabel() == "scan-map agreement"
    assert axes[-1].get_xlabel() == "time since start (s)"


def test_error_figure_without_truth_shows_agreement_only(tmp_path, figures):
    t = np.linspace(0, 5, 50)
    plots.plot_errors(tmp_path / "error.png", 0.0, agreement_t=t, agreement=np.full_like(t, 0.8))
    axes = figures[-1].axes
    assert [a.get_ylabel() for a in axes] == ["scan-map agreement"]


def test_trajectory_draws_truth_reference_estimate_and_start(tmp_path, figures):
    est = np.column_stack([np.linspace(1, 8, 50), np.full(50, 1.5), np.zeros(50)])
    ref = est + [0.0, 0.05, 0.0]
    truth = est - [0.0, 0.05, 0.0]
    plots.plot_trajectory(tmp_path / "t.png", corridor_map(), est, truth, (1.0, 1.5, 0.0), reference_poses=ref)
    ax = figures[-1].axes[0]
    labels = _legend(ax)
    for want in ("ground truth", "reference track (scan matches)", "estimate", "initial pose"):
        assert want in labels, labels
    drawn = [line for line in ax.lines if line.get_label() == "reference track (scan matches)"][0]
    assert np.allclose(drawn.get_xdata(), ref[:, 0]) and np.allclose(drawn.get_ydata(), ref[:, 1])
    assert ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"


def test_replay_with_a_reference_draws_it(tmp_path, figures):
    """A replay that computed a reference track draws it in trajectory.png, and with ground truth
    error.png has the along-/cross-track panel."""
    from localization.eval.datasets import sim_bag
    from localization.tools import replay

    bag = sim_bag("trial1_noise0", duration=3.0)
    out = tmp_path / "out"
    assert replay.main([str(bag), "--map", "stata_basement", "--params", "params", "--particles", "200",
                        "-p", "num_beams_per_particle:=30", "--reference", "--quiet", "--out", str(out)]) == 0
    assert (out / "trajectory.png").is_file() and (out / "error.png").is_file()
    by_labels = {tuple(_legend(f.axes[0])): f for f in figures}
    traj = [f for labels, f in by_labels.items() if "estimate" in labels]
    assert traj and "reference track (scan matches)" in _legend(traj[0].axes[0])
    assert "ground truth" in _legend(traj[0].axes[0])
    err = [f for f in figures if f.axes[0].get_ylabel() == "position error (m)"]
    assert err and any(any(label.startswith("along-track") for label in _legend(a)) for a in err[0].axes)
