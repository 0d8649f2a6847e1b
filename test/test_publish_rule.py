"""One publish rule (``core.publish_rule``) for the node's output streams and the feed loop's log:
forward in time, a clock that went back by more than TIME_JUMP restarts the stream."""
from __future__ import annotations

import math

import numpy as np
import pytest

from localization.core.localizer.timeline import PoseEstimate
from localization.core.publish_rule import TIME_JUMP, ForwardInTime, Verdict

# stamps offered to a stream, and what goes out: equal and older ones are not published; 0.5 is
# more than TIME_JUMP behind 2.0 (a bag played again): the stream starts again from it
OFFERED = [1.0, 1.5, 1.5, 1.2, 2.0, 0.5, 0.6, 0.6, math.nan, 0.7]
PUBLISHED = [1.0, 1.5, 2.0, 0.5, 0.6, 0.7]


def _estimate(t: float, x: float = 0.0) -> PoseEstimate:
    return PoseEstimate(stamp=t, pose=np.array([x, 0.0, 0.0]), covariance=np.eye(3) * 0.01)


def test_the_rule_publishes_newer_restarts_after_a_jump_back_and_drops_the_rest():
    rule = ForwardInTime()
    verdicts = [rule.admit(t) for t in OFFERED]
    assert verdicts == [Verdict.NEWER, Verdict.NEWER, Verdict.SAME, Verdict.OLDER, Verdict.NEWER, Verdict.RESTART,
                        Verdict.NEWER, Verdict.SAME, Verdict.OLDER, Verdict.NEWER]
    assert [t for t, v in zip(OFFERED, verdicts) if v.published] == PUBLISHED
    assert rule.last == 0.7
    assert rule.judge(0.7 - TIME_JUMP + 0.01) is Verdict.OLDER and rule.last == 0.7  # judge changes nothing
    rule.reset()
    assert rule.admit(-5.0) is Verdict.NEWER


def test_the_feed_logs_what_the_rule_publishes_and_keeps_the_newest_pose_of_an_instant():
    from localization.eval.feed import Feeder

    class OdometryOnly:  # a Localizer stand-in: each odometry call returns the next estimate
        def __init__(self, estimates):
            self.estimates = iter(estimates)

        def on_odometry(self, twist):
            return next(self.estimates)

        def take_corrections(self):
            return []

        def take_costs(self):
            return []

    estimates = [_estimate(t, x=k) for k, t in enumerate(OFFERED)]
    feeder = Feeder(OdometryOnly(estimates))
    for _ in estimates:
        feeder.odometry(None)
    assert feeder.log.est_t == PUBLISHED
    # the second estimate of 1.5 (x = 2) replaced the first (x = 1); the second of 0.6 (x = 7) the first
    assert [p[0] for p in feeder.log.est_poses] == [0.0, 2.0, 4.0, 5.0, 7.0, 9.0]


def test_the_node_outputs_publish_what_the_rule_publishes():
    pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message

    from localization.core.parameters import Parameters
    from localization.ros.latency import LatencyBook
    from localization.ros.outputs import Outputs
    from localization.ros.stamps import StampBook

    class Recorder:
        def __init__(self):
            self.sent = []

        def publish(self, msg):
            self.sent.append(msg)

    class Log:
        def __init__(self):
            self.lines = []

        def info(self, line, **_):
            self.lines.append(line)

        warning = info

    class FakeNode:
        def __init__(self):
            self.log = Log()

        def create_publisher(self, *_):
            return Recorder()

        def get_logger(self):
            return self.log

    class Corrections:  # a Localizer stand-in: the corrections of one call
        health, batch = 0.9, []

        def take_corrections(self):
            out, self.batch = self.batch, []
            return out

        def particles(self):
            return np.zeros((3, 3))

    class Watchdog:
        def sensor_update(self, now, phases):
            pass

    node, loc = FakeNode(), Corrections()
    out = Outputs(node, Parameters(publish_tf="none", max_particles_published=0), loc, StampBook(), Watchdog(),
                  LatencyBook())
    for t in OFFERED:
        out.publish_odom_pose(_estimate(t), None)

    def stamps(sent, kind):  # the poses go out serialized
        msgs = [deserialize_message(raw, kind) for raw in sent]
        return [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs]
    assert stamps(out.pose_pub.sent, Odometry) == pytest.approx(PUBLISHED)
    loc.batch = [_estimate(t) for t in OFFERED]  # the same stamps as corrections on /pf/pose
    assert out.publish_corrections() == len(PUBLISHED)
    assert stamps(out.pose_cov_pub.sent, PoseWithCovarianceStamped) == pytest.approx(PUBLISHED)
    restarts = [line for line in node.log.lines if "went back by 1.50 s" in line]
    assert len(restarts) == 2  # one per stream
