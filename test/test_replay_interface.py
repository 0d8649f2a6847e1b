"""localization-replay as a new user meets it: a map image, a parameter file by name, a
real bag without --params, an existing --out folder, the MCAP export of the run, and the figures
(error.png's axes and legend, the initial-pose arrow under the track, the convergence line)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from localization.bags import open_bag
from localization.eval import plots
from localization.eval.datasets import REAL_BAGS, real_bag_path
from localization.tools import replay as R


def test_map_image_is_refused_with_the_yaml_to_give(capsys):
    with pytest.raises(SystemExit) as exc:
        R.main(["some.bag", "--map", "basement_fixed.png"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "basement_fixed.yaml" in err and "Traceback" not in err


def test_params_by_name(tmp_path, capsys):
    assert R.main([str(tmp_path / "none.bag"), "--map", "basement_fixed", "--params", "real_params"]) == 1
    err = capsys.readouterr().err
    assert "bag not found" in err and "parameter file" not in err  # real_params was found
    assert R.main([str(tmp_path / "none.bag"), "--map", "basement_fixed", "--params", "no_such_params"]) == 1
    assert "parameter file not found" in capsys.readouterr().err


def test_real_bag_without_params_uses_the_car_parameters_and_writes_an_mcap(tmp_path, capsys):
    name = "bag3"
    bag, start = real_bag_path(name), REAL_BAGS[name].start
    out = tmp_path / "out"
    args = [str(bag), "--map", REAL_BAGS[name].map, "--initial-pose", ",".join(map(str, start)), "--particles",
            "300", "--no-plots", "--no-reference", "--quiet", "--out", str(out)]
    assert R.main(args + ["--mcap"]) == 0
    err = capsys.readouterr().err
    assert "real_params" in err and "/vesc/odom" in err  # said, not silent
    m = json.loads((out / "metrics.json").read_text())
    assert m["odom_topic"] == "/vesc/odom"
    with open_bag(out / "run_mcap") as b:
        infos = b.topic_infos
        for topic in ("/map", "/scan", "/pf/particles", "/pf/pose/odom", "/pf/track", "/tf", "/tf_static"):
            assert topic in infos and infos[topic].count > 0, topic
        assert infos["/scan"].count == m["scans"] if "scans" in m else infos["/scan"].count > 100
        assert infos["/map"].latched
        last = None
        for msg in b.messages(["/pf/pose/odom"]):
            last = msg.msg
        assert last is not None and last.header.frame_id == "map"
    # an existing --out folder is refused, unless --force
    assert R.main(args) == 1
    assert "exists already" in capsys.readouterr().err
    assert R.main(args + ["--force"]) == 0


class _Capture:
    def __init__(self, monkeypatch):
        import matplotlib.figure
        self.figs = []
        original = matplotlib.figure.Figure.savefig

        def savefig(fig, *a, **k):
            self.figs.append(fig)
            return original(fig, *a, **k)
        monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)


def test_error_plot_axis_covers_the_trace_and_heading_has_its_own_axis(tmp_path, monkeypatch):
    cap = _Capture(monkeypatch)
    t = np.linspace(0, 10, 200)
    ct = 0.05 + 0.02 * np.sin(t)  # well below the 0.2 m line
    plots.plot_errors(tmp_path / "e.png", 0.0, t, ct, np.full_like(t, 0.05), t, np.full_like(t, 0.9))
    ax = cap.figs[-1].axes[0]
    assert ax.get_ylim()[1] > 0.2 * 1.2  # the threshold line is not the top edge
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert any(label.startswith("position error") for label in labels)
    heading = [a for a in cap.figs[-1].axes if a.get_ylabel() == "heading error (deg)"]
    assert heading and heading[0] is not ax  # heading on its own axis, not over the metre scale
    big = np.r_[ct, 1.5]
    plots.plot_errors(tmp_path / "e2.png", 0.0, np.r_[t, 10.1], big)
    assert cap.figs[-1].axes[0].get_ylim()[1] >= 1.5  # the whole trace is visible


def test_initial_pose_arrow_is_under_the_track(tmp_path, monkeypatch):
    from helpers import corridor_map
    cap = _Capture(monkeypatch)
    est = np.column_stack([np.linspace(1, 8, 50), np.full(50, 1.5), np.zeros(50)])
    plots.plot_trajectory(tmp_path / "t.png", corridor_map(), est, initial_pose=(1.0, 1.5, 0.0))
    ax = cap.figs[-1].axes[0]
    arrow = [p for p in ax.patches if p.get_label() == "initial pose"][0]
    track = [line for line in ax.lines if line.get_label() == "estimate"][0]
    assert arrow.get_zorder() < track.get_zorder()
    assert arrow.get_facecolor()[3] == 0.0  # an outline: the start of the track shows through


def test_convergence_at_once_reads_as_such():
    from localization.eval.replay import summary_table
    metrics = _fake_metrics(time_to_converge_s=0.001)
    text = summary_table(metrics)
    assert "at the first estimate" in text and "0.00 s" not in text
    assert "after 1.50 s" in summary_table(_fake_metrics(time_to_converge_s=1.5))


def _fake_metrics(**over):
    """A metrics dict as compute_metrics makes it (the keys summary_table reads)."""
    stats = {"mean": 0.05, "median": 0.04, "p95": 0.1, "max": 0.2, "rms": 0.06, "p05": 0.7, "min": 0.5}
    m = {"bag": "b", "initial_pose_source": "--initial-pose", "scans": 10, "odometry": 10, "estimates": 20,
         "sensor_updates": 10, "has_truth": True, "ct_error_m": stats, "heading_error_mean_abs_rad": 0.01,
         "time_to_converge_s": 0.0, "converge_threshold_m": 0.2, "scan_map_agreement": stats, "health": stats,
         "recoveries": 0, "max_jump_m": 0.1, "sensor_update_ms": {"median_ms": 1.0, "p95_ms": 2.0},
         "motion_update_ms": {"median_ms": 0.1, "p95_ms": 0.2}, "num_particles": 100, "num_beams_per_particle": 100,
         "ray_caster": "lookup_table", "effective_update_rate_hz": 100.0, "realtime_factor": 2.0,
         "bag_duration_s": 1.0, "wall_time_s": 0.5, "particles": None, "truth_source": "/tf"}
    m.update(over)
    return m


# --------------------------------------------------------------------------------------------
# A bag without an odometry topic: odometry from /tf odom -> base_link, the laser mount from TF
# --------------------------------------------------------------------------------------------


class _Info:
    def __init__(self, msgtype, count=10):
        self.msgtype, self.count = msgtype, count


def test_check_topics_accepts_tf_odometry_only_without_the_topic():
    from localization.eval.replay import ReplayError, check_topics, tf_odometry
    scan = {"/base_scan": _Info("sensor_msgs/msg/LaserScan")}
    ros1_tf = {**scan, "/tf": _Info("tf/msg/tfMessage")}
    assert tf_odometry(ros1_tf, "/odom")
    check_topics(ros1_tf, "b.bag", "/base_scan", "/odom", None, "/initialpose", False)  # no error
    with pytest.raises(ReplayError, match="odometry topic /odom not in bag"):
        check_topics(scan, "b.bag", "/base_scan", "/odom", None, "/initialpose", False)
    # an odometry topic of the wrong type is still an error, /tf or not
    wrong = {**ros1_tf, "/odom": _Info("geometry_msgs/msg/PoseStamped")}
    assert not tf_odometry(wrong, "/odom")
    with pytest.raises(ReplayError, match="expected nav_msgs/msg/Odometry"):
        check_topics(wrong, "b.bag", "/base_scan", "/odom", None, "/initialpose", False)


def test_tf_odometry_events_come_in_order_with_the_scans():
    from localization.core.odometry import TwistData
    from localization.core.scan import ScanData
    from localization.eval.datasets import bag_odometry
    from localization.eval.replay import bag_events
    path = real_bag_path("lgfloor2")
    odo = bag_odometry(path, "/odom")
    assert odo.source == "/tf odom -> base_link" and len(odo.messages) > 1000
    with open_bag(path) as bag:
        events = list(bag_events(bag, ["/base_scan"], "/base_scan", "/odom", None, None, ("map", "base_link"),
                                 [], [], odometry=odo))
    twists = [e for e in events if isinstance(e, TwistData)]
    scans = [e for e in events if isinstance(e, ScanData)]
    assert len(twists) == len(odo.messages) and len(scans) == 1640
    stamps = np.array([e.stamp for e in twists])
    assert np.all(np.diff(stamps) > 0)  # TF odometry in stamp order
    # interleaved with the scans by record time: odometry and scans alternate, not one block after the other
    kinds = np.array([isinstance(e, ScanData) for e in events])
    assert np.count_nonzero(np.diff(kinds.astype(int))) > 1000
    assert np.any(np.hypot(np.array([e.vx for e in twists]), np.array([e.vy for e in twists])) > 0.1)  # it moves


def test_bag_without_odometry_topic_replays_from_tf(tmp_path, capsys):
    out = tmp_path / "out"
    assert R.main([str(real_bag_path("lgfloor2")), "--map", "lgfloor", "--params", "pioneer_params", "--global",
                   "--particles", "300", "-p", "global_num_particles=5000", "--no-plots", "--no-reference",
                   "--quiet", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "odometry from /tf odom -> base_link" in ln]
    assert len(lines) == 1, err  # said once, in one line
    assert "laser pose in base_link from the bag's TF" in err
    m = json.loads((out / "metrics.json").read_text())
    assert m["odom_topic"] == "/tf odom -> base_link" and m["odometry"] > 1000 and m["scans"] == 1640
    assert m["laser_source"] == "tf" and m["laser_offset"] == pytest.approx([0.135, 0.0, 0.0], abs=1e-9)
    assert m["sensor_updates"] > 500
