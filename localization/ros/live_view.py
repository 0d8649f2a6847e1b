"""A live view of the filter in the Foxglove app (a browser, no ROS install): the map, each scan,
the particle cloud, the estimate, its track, a reference track and TF, served over the Foxglove
WebSocket protocol (``foxglove.websocket.v1``) by the ``foxglove-sdk`` package
(``pip install foxglove-sdk``). Fed core data only (``OccupancyMap``, ``ScanData``, pose arrays,
the ``Localizer``), so the replay tool and the node use it alike. It imports no ROS module: it
sits in the ``ros/`` layer, the adapters to the outside world, so that the node may use it.

    live = LiveView(port=8765)                  # binds 127.0.0.1:8765 (port 0: any free port)
    live.set_map(occupancy_map)                 # kept, and sent again to every new subscriber
    live(scan, localizer)                       # after each scan: scan, cloud, estimate, TF
    live.set_reference(t, poses)                # kept like the map
    live.close()

In the app: Open connection → Foxglove WebSocket → ``ws://127.0.0.1:8765``, then a 3D panel with
the display frame ``map``.

Channels (topic: Foxglove schema). Stamps are the time the data describes, on the clock of the
data fed in (bag time in a replay; the node's scan clock live); each message's log time is the
same instant in nanoseconds. The last message of every topic but /scan is kept and sent again to
each new subscriber (a viewer that connects late, or after a replay, sees the map and the state)::

    /map               foxglove.Grid             int8 field "occupancy" per cell, as nav_msgs/OccupancyGrid
                                                 (-1 unknown, 0 free … 100 occupied), row 0 at the origin
    /scan              foxglove.LaserScan        in the scan's frame (default "laser"), stamp = first beam
    /pf/particles      foxglove.PosesInFrame     map frame, ≤ max_particles, at most every cloud_period s
    /pf/pose           foxglove.PoseInFrame      map frame, the estimate at the scan's time (mid-sweep)
    /pf/track          foxglove.SceneUpdate      a line through the estimates so far, every track_period s
    /reference/track   foxglove.SceneUpdate      a line through a reference (or ground-truth) track
    /tf                foxglove.FrameTransforms  map → base frame at the estimate's time, base → laser (mount)

Pacing: with ``rate`` > 0 each scan is held back until ``(stamp − first stamp) / rate`` seconds of
wall time have passed since the first scan (``rate`` 1: the bag's own speed); ``rate`` 0 feeds as
fast as it comes (the node's case: live data comes at its own pace).
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from localization.core.geometry import yaw_to_quaternion
from localization.core.occupancy_map import OccupancyMap

DEFAULT_PORT = 8765
DEFAULT_HOST = "127.0.0.1"  # this machine only; "0.0.0.0" serves the network
MAX_PARTICLES = 1000  # poses per cloud message
CLOUD_PERIOD_S = 0.1  # s of data time between clouds
TRACK_PERIOD_S = 1.0  # s of data time between track messages
TRACK_SPACING_S = 0.1  # s: at most one track point per this much data time
LINE_WIDTH_M = 0.05
RESEND_DELAY_S = 0.05  # wait between a new subscription and re-sending a kept message to it

TOPICS = {"map": "/map", "scan": "/scan", "particles": "/pf/particles", "estimate": "/pf/pose",
          "track": "/pf/track", "reference": "/reference/track", "tf": "/tf"}


class LiveViewError(RuntimeError):
    """The live view cannot start (foxglove-sdk missing, port taken): one line."""


def _ns(t: float) -> int:
    return max(0, int(round(float(t) * 1e9)))


class _Listener:
    """foxglove ServerListener: a subscription to a kept topic asks for that message again."""

    def __init__(self, view: "LiveView"):
        self.view = view

    def on_subscribe(self, client, channel) -> None:  # noqa: ARG002 - the SDK's callback signature
        self.view._request_resend(channel.topic)

    def on_unsubscribe(self, client, channel) -> None:  # noqa: ARG002
        return None


class LiveView:
    """The Foxglove WebSocket server and its channels (module docstring). Also the replay's
    ``on_scan(scan, localizer)`` hook (``__call__``)."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = DEFAULT_HOST, map_frame: str = "map",
                 base_frame: str = "base_link_pf", rate: float = 0.0, max_particles: int = MAX_PARTICLES,
                 cloud_period: float = CLOUD_PERIOD_S, track_period: float = TRACK_PERIOD_S,
                 name: str = "localization"):
        try:
            import foxglove
            import foxglove.channels as ch
            import foxglove.messages as messages
        except ImportError:
            raise LiveViewError("the live view needs the foxglove-sdk package: pip install foxglove-sdk "
                                "(or pip install 'localization[live]')") from None
        self._m = messages
        self.map_frame, self.base_frame = map_frame, base_frame
        self.rate = float(rate)
        self.max_particles, self.cloud_period, self.track_period = int(max_particles), cloud_period, track_period
        self._context = foxglove.Context()
        ctx = self._context
        self.channels = {
            "map": ch.GridChannel(TOPICS["map"], context=ctx),
            "scan": ch.LaserScanChannel(TOPICS["scan"], context=ctx),
            "particles": ch.PosesInFrameChannel(TOPICS["particles"], context=ctx),
            "estimate": ch.PoseInFrameChannel(TOPICS["estimate"], context=ctx),
            "track": ch.SceneUpdateChannel(TOPICS["track"], context=ctx),
            "reference": ch.SceneUpdateChannel(TOPICS["reference"], context=ctx),
            "tf": ch.FrameTransformsChannel(TOPICS["tf"], context=ctx),
        }
        self._kept: dict = {}  # topic -> (message, log_time ns): sent again to each new subscriber
        self._lock = threading.Lock()
        self._resend: set = set()
        self._wake = threading.Event()
        self._closed = threading.Event()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=int(port), context=ctx,
                                                server_listener=_Listener(self))
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types: one line
            raise LiveViewError(f"cannot serve the live view on {host}:{port}: {' '.join(str(exc).split())}") \
                from None
        self.host, self.port = host, int(self.server.port)
        self._thread = threading.Thread(target=self._resender, name="live-view-resend", daemon=True)
        self._thread.start()
        self._wall0 = None  # (wall clock, data stamp) of the first scan: the pacing origin
        self._last_cloud = -math.inf
        self._last_track = -math.inf
        self._track_t: list = []
        self._track_p: list = []

    # ------------------------------------------------------------------ kept messages
    def _keep(self, key: str, message, stamp: float) -> None:
        """Send ``message`` and keep it: a new subscriber of the topic gets the latest one."""
        topic = TOPICS[key]
        with self._lock:
            self._kept[topic] = (key, message, _ns(stamp))
        self.channels[key].log(message, log_time=_ns(stamp))

    def _request_resend(self, topic: str) -> None:
        with self._lock:
            if topic not in self._kept:
                return
            self._resend.add(topic)
        self._wake.set()

    def _resender(self) -> None:
        while not self._closed.is_set():
            if not self._wake.wait(0.5):
                continue
            self._wake.clear()
            time.sleep(RESEND_DELAY_S)  # the subscription is registered after the callback returns
            with self._lock:
                todo = [self._kept[t] for t in self._resend if t in self._kept]
                self._resend.clear()
            for key, message, log_time in todo:
                if not self._closed.is_set():
                    self.channels[key].log(message, log_time=log_time)

    # ------------------------------------------------------------------ building blocks
    def _pose(self, x: float, y: float, yaw: float):
        m = self._m
        q = yaw_to_quaternion(float(yaw))
        return m.Pose(position=m.Vector3(x=float(x), y=float(y), z=0.0),
                      orientation=m.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))

    def _stamp(self, t: float):
        return self._m.Timestamp.from_epoch_secs(max(float(t), 0.0))

    def _line(self, entity_id: str, t: float, poses, color) -> object:
        m = self._m
        pts = [m.Point3(x=float(x), y=float(y), z=0.02) for x, y in np.asarray(poses, dtype=float)[:, :2]]
        line = m.LinePrimitive(type=m.LinePrimitiveLineType.LineStrip, thickness=LINE_WIDTH_M, points=pts,
                               color=m.Color(r=color[0], g=color[1], b=color[2], a=1.0))
        entity = m.SceneEntity(timestamp=self._stamp(t), frame_id=self.map_frame, id=entity_id, lines=[line])
        return m.SceneUpdate(entities=[entity])

    # ------------------------------------------------------------------ what is shown
    def set_map(self, occupancy_map: OccupancyMap, stamp: float = 0.0) -> None:
        """The map (kept: every new subscriber of /map gets it)."""
        m = self._m
        ox, oy, oyaw = (float(v) for v in occupancy_map.origin)
        data = np.ascontiguousarray(occupancy_map.data, dtype=np.int8)
        grid = m.Grid(timestamp=self._stamp(stamp), frame_id=self.map_frame, pose=self._pose(ox, oy, oyaw),
                      column_count=int(occupancy_map.width),
                      cell_size=m.Vector2(x=occupancy_map.resolution, y=occupancy_map.resolution),
                      row_stride=int(occupancy_map.width), cell_stride=1,
                      fields=[m.PackedElementField(name="occupancy", offset=0,
                                                   type=m.PackedElementFieldNumericType.Int8)],
                      data=data.tobytes())
        self._keep("map", grid, stamp)

    def set_reference(self, t, poses, label: str = "reference") -> None:
        """A reference (or ground-truth) track, drawn as a green line (kept like the map)."""
        t = np.asarray(t, dtype=float)
        p = np.asarray(poses, dtype=float).reshape(-1, 3)
        ok = np.all(np.isfinite(p), axis=1) & np.isfinite(t)
        if not ok.any():
            return
        t, p = t[ok], p[ok]
        self._keep("reference", self._line(label, float(t[-1]), p, (0.1, 0.75, 0.2)), float(t[-1]))

    def publish_scan(self, scan, laser_frame: str | None = None) -> None:
        m = self._m
        ranges = np.asarray(scan.ranges, dtype=float)
        ranges = np.where(np.isfinite(ranges), ranges, 0.0)  # no return: 0, drawn as nothing
        n = ranges.size
        msg = m.LaserScan(timestamp=self._stamp(scan.stamp), frame_id=laser_frame or scan.frame_id or "laser",
                          pose=self._pose(0.0, 0.0, 0.0), start_angle=float(scan.angle_min),
                          end_angle=float(scan.angle_min + (n - 1) * scan.angle_increment),
                          ranges=ranges.tolist())
        self.channels["scan"].log(msg, log_time=_ns(scan.stamp))

    def publish_particles(self, stamp: float, particles) -> None:
        p = np.asarray(particles, dtype=float).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p) > self.max_particles:
            p = p[np.linspace(0, len(p) - 1, self.max_particles).round().astype(np.intp)]
        msg = self._m.PosesInFrame(timestamp=self._stamp(stamp), frame_id=self.map_frame,
                                   poses=[self._pose(*row) for row in p])
        self._keep("particles", msg, stamp)

    def publish_estimate(self, stamp: float, pose, laser_offset=(0.0, 0.0, 0.0), laser_frame: str = "laser") -> None:
        """The estimate (PoseInFrame), TF map → base frame and base frame → laser, and the track."""
        pose = np.asarray(pose, dtype=float)
        if not np.all(np.isfinite(pose)):
            return
        m = self._m
        self._keep("estimate", m.PoseInFrame(timestamp=self._stamp(stamp), frame_id=self.map_frame,
                                             pose=self._pose(*pose)), stamp)
        tfs = [self._transform(stamp, self.map_frame, self.base_frame, pose),
               self._transform(stamp, self.base_frame, laser_frame, laser_offset)]
        self._keep("tf", m.FrameTransforms(transforms=tfs), stamp)
        if not self._track_t or stamp - self._track_t[-1] >= TRACK_SPACING_S:
            self._track_t.append(float(stamp))
            self._track_p.append(pose.copy())
        if stamp - self._last_track >= self.track_period:
            self._publish_track()

    def _publish_track(self) -> None:
        if len(self._track_p) > 1:
            stamp = self._track_t[-1]
            self._keep("track", self._line("estimate", stamp, np.array(self._track_p), (0.9, 0.2, 0.1)), stamp)
            self._last_track = stamp

    def _transform(self, stamp, parent, child, pose):
        m = self._m
        q = yaw_to_quaternion(float(pose[2]))
        return m.FrameTransform(timestamp=self._stamp(stamp), parent_frame_id=parent, child_frame_id=child,
                                translation=m.Vector3(x=float(pose[0]), y=float(pose[1]), z=0.0),
                                rotation=m.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))

    # ------------------------------------------------------------------ the replay's hook
    def pace(self, stamp: float) -> None:
        """Hold back until ``stamp`` is due at ``rate`` x real time (module docstring)."""
        if not (self.rate > 0 and math.isfinite(stamp)):
            return
        now = time.monotonic()
        if self._wall0 is None:
            self._wall0 = (now, float(stamp))
            return
        due = self._wall0[0] + (float(stamp) - self._wall0[1]) / self.rate
        if due > now:
            time.sleep(min(due - now, 1.0))  # a gap in the bag is not waited out in full

    def __call__(self, scan, localizer) -> None:
        """After each scan the localizer took: pace, then the scan, the cloud, the estimate, TF."""
        self.pace(scan.stamp)
        frame = scan.frame_id or "laser"
        self.publish_scan(scan, frame)
        if not localizer.ready:
            return
        t = localizer.scan_time(scan)
        est = localizer.estimate_at(t)
        if est is not None:
            self.publish_estimate(est.stamp, est.pose, localizer.laser_offset, frame)
        if scan.stamp - self._last_cloud >= self.cloud_period:
            self.publish_particles(t, localizer.particles())
            self._last_cloud = scan.stamp

    def finish(self, res) -> None:
        """After a replay (``ReplayResult``): the whole estimate track, and its reference track, else
        its ground truth. Each topic's last message is kept for viewers that connect later."""
        self._publish_track()
        ref = getattr(res, "reference", None)
        if ref is not None:
            self.set_reference(*ref.good_track())
        elif getattr(res, "has_truth", False):
            self.set_reference(res.truth_t, res.truth_poses, label="ground truth")

    # ------------------------------------------------------------------ lifetime
    def wait(self, timeout: float | None = None) -> None:
        """Serve until ``close()`` (or Ctrl-C in the caller), or for ``timeout`` seconds."""
        self._closed.wait(timeout)

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._wake.set()
        self.server.stop()
        self._thread.join(timeout=2.0)

    def __enter__(self) -> "LiveView":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def start_live_view(params, log) -> LiveView | None:
    """The node's live view when ``foxglove_port`` >= 0 (one line says where, or why not), else None."""
    if params.foxglove_port < 0:
        return None
    try:
        view = LiveView(port=params.foxglove_port, host=params.foxglove_host, map_frame=params.map_frame,
                        base_frame=params.particle_filter_frame)
    except LiveViewError as exc:
        log.error(f"live view not started: {exc}")
        return None
    log.info(f"live view: Foxglove WebSocket on ws://{view.host}:{view.port}")
    return view


__all__ = ["DEFAULT_HOST", "DEFAULT_PORT", "LiveView", "LiveViewError", "TOPICS", "start_live_view"]
