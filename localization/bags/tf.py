"""Transforms read from a bag's ``/tf`` and ``/tf_static``: odometry from ``odom → base_link`` and
the laser's mount in ``base_link``.

Frame names are compared without a leading ``/`` (ROS 1 bags say ``/base_link``). Both TF message
types carry the same ``transforms`` list: ``tf2_msgs/msg/TFMessage`` and ROS 1's ``tf/msg/tfMessage``.
Stamps are the transforms' header stamps (float s on the bag's clock), never the record times.

Chains: a frame's parent is its latest published parent; a chain child → … → parent is composed in
3D (quaternions), then projected onto the plane: (x, y, yaw of the child's x axis), and
``upright`` = the child's z axis points up (R₃₃ > 0; a lidar mounted upside down mirrors its scan).
Every edge of a chain but one (the moving ``odom → base_link``) must be constant: its first sample is used.

Odometry from TF: poses P_k of base_link in odom at stamps τ_k, made into the twist stream a
nav_msgs/Odometry topic would give (the core's convention: the twist stamped τ_k holds over
(τ_{k−1}, τ_k]) by inverting ``integrate_twist`` exactly, at the TF rate::

    Δ_k = P_{k−1}⁻¹ ⊕ P_k = (dx, dy, dθ),   dt = τ_k − τ_{k−1},   ω = dθ / dt
    (dx, dy)ᵀ = [[a, −b], [b, a]] (v_x, v_y)ᵀ,   a = sin(dθ)/ω,  b = (1 − cos dθ)/ω
    ⇒ (v_x, v_y)ᵀ = [[a, b], [−b, a]] (dx, dy)ᵀ / (a² + b²)

(a → dt, b → dt·dθ/2 as dθ → 0). Repeated stamps (dt ≤ 0) are dropped; the first pose gives a
zero twist at its own stamp (where the stream starts).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.bags.reader import BagError, BagReader, open_bag
from localization.core.geometry import wrap_angle
from localization.core.odometry import TwistData

TF_TOPICS = ("/tf_static", "/tf")
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
MAX_HOPS = 16


def _strip(frame: str) -> str:
    return str(frame).lstrip("/")


def _stamp(h) -> float:
    return float(h.stamp.sec) + 1e-9 * float(h.stamp.nanosec)


# --------------------------------------------------------------------------------------------
# Quaternions (x, y, z, w), vectorised over leading axes
# --------------------------------------------------------------------------------------------


def quat_multiply(a, b) -> np.ndarray:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quat_rotate(q, v) -> np.ndarray:
    """Vector(s) v rotated by unit quaternion(s) q."""
    q, v = np.asarray(q, dtype=float), np.asarray(v, dtype=float)
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def planar(translation, quaternion) -> tuple[np.ndarray, np.ndarray]:
    """3D transform(s) → planar (x, y, yaw of the x axis) (…, 3) and upright flag(s)."""
    q = np.asarray(quaternion, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    ex = quat_rotate(q, np.array([1.0, 0.0, 0.0]))
    ez = quat_rotate(q, np.array([0.0, 0.0, 1.0]))
    t = np.asarray(translation, dtype=float)
    return np.stack([t[..., 0], t[..., 1], np.arctan2(ex[..., 1], ex[..., 0])], axis=-1), ez[..., 2] > 0


# --------------------------------------------------------------------------------------------
# Reading the transforms
# --------------------------------------------------------------------------------------------


@dataclass
class TfEdge:
    """One parent → child edge: stamps (N,), translations (N, 3), rotations (N, 4: x, y, z, w), the
    record time (ns) of each sample's message, in stamp order."""

    parent: str
    child: str
    stamps: np.ndarray
    translations: np.ndarray
    rotations: np.ndarray
    static: bool
    record_ns: np.ndarray

    def first(self) -> tuple[np.ndarray, np.ndarray]:
        return self.translations[0], self.rotations[0]


class TfTree:
    """Every edge of a bag's /tf and /tf_static (``read_tf``)."""

    def __init__(self, edges: dict[str, TfEdge]):
        self.edges = edges  # child -> edge (the child's latest parent)

    def __contains__(self, child: str) -> bool:
        return _strip(child) in self.edges

    def chain(self, parent: str, child: str) -> list[TfEdge]:
        """The edges from ``parent`` down to ``child`` (root first); raises BagError without one."""
        parent, child = _strip(parent), _strip(child)
        out: list[TfEdge] = []
        frame = child
        while frame != parent:
            edge = self.edges.get(frame)
            if edge is None or len(out) >= MAX_HOPS:
                known = ", ".join(sorted(f"{e.parent} -> {c}" for c, e in self.edges.items())) or "none"
                raise BagError(f"no TF chain {parent} -> {child} in the bag (transforms: {known})")
            out.append(edge)
            frame = edge.parent
        return out[::-1]

    def constant(self, parent: str, child: str) -> tuple[np.ndarray, bool]:
        """Planar pose (x, y, yaw) of ``child`` in ``parent`` from the first sample of each edge, and
        whether the child is upright."""
        t, q = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        for e in self.chain(parent, child):
            et, eq = e.first()
            t = t + quat_rotate(q, et)
            q = quat_multiply(q, eq)
        pose, upright = planar(t, q)
        return pose, bool(upright)


def read_tf(bag: BagReader) -> TfTree:
    """Every transform on /tf_static and /tf of an open bag (types ``TF_TYPES``)."""
    infos = bag.topic_infos
    topics = [t for t in TF_TOPICS if t in infos and infos[t].msgtype in TF_TYPES]
    raw: dict[str, dict] = {}
    for m in bag.messages(topics):
        static = m.topic == "/tf_static"
        for tf in m.msg.transforms:
            child, parent = _strip(tf.child_frame_id), _strip(tf.header.frame_id)
            if not child or child == parent:
                continue
            e = raw.get(child)
            if e is None or e["parent"] != parent:  # a new parent replaces the old one
                e = raw[child] = {"parent": parent, "t": [], "tr": [], "q": [], "rec": [], "static": static}
            tr, q = tf.transform.translation, tf.transform.rotation
            e["t"].append(_stamp(tf.header))
            e["rec"].append(m.t_ns)
            e["tr"].append((float(tr.x), float(tr.y), float(tr.z)))
            e["q"].append((float(q.x), float(q.y), float(q.z), float(q.w)))
            e["static"] = e["static"] and static
    edges = {}
    for child, e in raw.items():
        t = np.asarray(e["t"], dtype=float)
        order = np.argsort(t, kind="stable")
        q = np.asarray(e["q"], dtype=float).reshape(-1, 4)[order]
        n = np.linalg.norm(q, axis=1, keepdims=True)
        q = np.where(n > 0, q / np.where(n > 0, n, 1.0), [0.0, 0.0, 0.0, 1.0])
        edges[child] = TfEdge(e["parent"], child, t[order], np.asarray(e["tr"], dtype=float).reshape(-1, 3)[order],
                              q, bool(e["static"]), np.asarray(e["rec"], dtype=np.int64)[order])
    return TfTree(edges)


# --------------------------------------------------------------------------------------------
# Odometry from TF
# --------------------------------------------------------------------------------------------


def twists_from_poses(t, poses) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (M,) and twists (M, 3: v_x, v_y, ω) that carry each pose to the next (module doc);
    the first row is a zero twist at the first stamp. Poses are taken in stamp order; a repeated
    stamp keeps its first pose."""
    t = np.asarray(t, dtype=float).ravel()
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    if t.size == 0:
        return t, np.zeros((0, 3))
    order = np.argsort(t, kind="stable")
    t, p = t[order], p[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, p = t[keep], p[keep]
    out = np.zeros((t.size, 3))
    if t.size > 1:
        dt = np.diff(t)
        c, s = np.cos(p[:-1, 2]), np.sin(p[:-1, 2])
        gx, gy = p[1:, 0] - p[:-1, 0], p[1:, 1] - p[:-1, 1]
        dx, dy = c * gx + s * gy, -s * gx + c * gy
        dth = wrap_angle(p[1:, 2] - p[:-1, 2])
        w = dth / dt
        small = np.abs(dth) < 1e-6
        wsafe = np.where(small, 1.0, w)
        a = np.where(small, dt * (1.0 - dth * dth / 6.0), np.sin(dth) / wsafe)
        b = np.where(small, dt * 0.5 * dth, (1.0 - np.cos(dth)) / wsafe)
        den = a * a + b * b
        out[1:, 0] = (a * dx + b * dy) / den
        out[1:, 1] = (-b * dx + a * dy) / den
        out[1:, 2] = w
    return t, out


def moving_edge(tree: TfTree, parent: str, child: str) -> TfEdge:
    """The one edge of the chain ``parent → child`` that moves (raises BagError otherwise)."""
    chain = tree.chain(parent, child)
    moving = [e for e in chain if len(e.stamps) > 1 and not e.static]
    if not moving:
        raise BagError(f"TF {parent} -> {child} never moves in the bag: no odometry in it")
    if len(moving) > 1:
        names = ", ".join(f"{e.parent} -> {e.child}" for e in moving)
        raise BagError(f"TF {parent} -> {child} has more than one moving edge ({names}): not odometry")
    return moving[0]


def tf_poses(tree: TfTree, parent: str, child: str) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (N,) and planar poses (N, 3) of ``child`` in ``parent``: the one moving edge of the
    chain sampled at its stamps, the constant edges composed around it (module doc)."""
    chain = tree.chain(parent, child)
    dyn = moving_edge(tree, parent, child)
    n = dyn.stamps.size
    t3, q = np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    for e in chain:
        et, eq = (dyn.translations, dyn.rotations) if e is dyn else e.first()
        t3 = t3 + quat_rotate(q, et)
        q = quat_multiply(q, eq)
    poses, _ = planar(t3, q)
    return dyn.stamps.copy(), poses


def odometry_from_tf(bag, odom_frame: str = "odom", base_frame: str = "base_link") -> list[TwistData]:
    """The twist stream (``TwistData``, stamps on the bag's clock) of TF ``odom_frame → base_frame``
    (module doc). ``bag``: a path or an open ``BagReader``. Raises BagError when the bag has no such TF."""
    if isinstance(bag, BagReader):
        tree = read_tf(bag)
    else:
        with open_bag(bag) as b:
            tree = read_tf(b)
    t, poses = tf_poses(tree, odom_frame, base_frame)
    t, tw = twists_from_poses(t, poses)
    frame = _strip(odom_frame)
    return [TwistData(stamp=float(s), vx=float(v[0]), vy=float(v[1]), wz=float(v[2]), frame_id=frame)
            for s, v in zip(t, tw)]


# --------------------------------------------------------------------------------------------
# The laser's mount
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LaserMount:
    """The laser's planar pose in the base frame, read from the bag's TF."""

    pose: tuple  # (x, y, yaw): m, m, rad
    upright: bool  # False: the lidar is upside down (its scan is mirrored in the base frame)
    frames: tuple  # (base_frame, laser_frame)

    def describe(self) -> str:
        x, y, yaw = self.pose
        return (f"laser pose in {self.frames[0]} from the bag's TF ({self.frames[1]}): x {x:.3f} m, y {y:.3f} m, "
                f"yaw {math.degrees(yaw):.1f} deg" + ("" if self.upright else ", UPSIDE DOWN (mirrored scan)"))


def laser_mount_from_bag(bag, scan_topic: str | None = None, base_frame: str = "base_link",
                         laser_frame: str | None = None) -> LaserMount | None:
    """The pose of the laser frame (``laser_frame``, else the frame_id of the first scan on
    ``scan_topic``) in ``base_frame`` from the bag's /tf_static and /tf, as the node looks it up;
    None when the bag does not carry it. ``bag``: a path or an open ``BagReader``."""
    if not isinstance(bag, BagReader):
        with open_bag(bag) as b:
            return laser_mount_from_bag(b, scan_topic, base_frame, laser_frame)
    if laser_frame is None:
        if scan_topic is None or scan_topic not in bag.topic_infos:
            return None
        for m in bag.messages([scan_topic]):
            laser_frame = _strip(m.msg.header.frame_id)
            break
    if not laser_frame:
        return None
    tree = read_tf(bag)
    if _strip(laser_frame) == _strip(base_frame):
        return LaserMount((0.0, 0.0, 0.0), True, (_strip(base_frame), _strip(laser_frame)))
    try:
        pose, upright = tree.constant(base_frame, laser_frame)
    except BagError:
        return None
    return LaserMount(tuple(float(v) for v in pose), upright, (_strip(base_frame), _strip(laser_frame)))
