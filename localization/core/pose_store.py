"""Pose persistence (opt-in, ``persist_pose``): the last estimate survives a restart.

The file is a small YAML document, written atomically (``paths.atomic_write``) so a crash while
writing leaves the previous pose::

    frame_id: map
    stamp: 1700000000.12          # seconds, the data time of the estimate
    pose: [x, y, yaw]             # m, m, rad
    covariance: [9 values]        # row-major 3x3 over x, y, yaw (m², m·rad, rad²)

``load_pose`` returns None (and the reason) for a missing, unreadable or non-finite file, so a
bad file never stops the node: it only means "no persisted pose".
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from localization.core.paths import atomic_write, cache_dir

DEFAULT_FILE_NAME = "last_pose.yaml"


@dataclass
class StoredPose:
    pose: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)
    frame_id: str
    stamp: float


def pose_file(configured: str = "") -> Path:
    """The configured file, or ``last_pose.yaml`` in the cache directory."""
    return Path(configured).expanduser() if configured else cache_dir() / DEFAULT_FILE_NAME


def save_pose(path, pose, covariance, frame_id: str, stamp: float) -> bool:
    """Write the pose; False (nothing written) when it is not finite."""
    pose = np.asarray(pose, dtype=float).reshape(3)
    cov = np.asarray(covariance, dtype=float).reshape(3, 3)
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov)) and math.isfinite(stamp)):
        return False
    text = (f"frame_id: {frame_id}\nstamp: {stamp!r}\n"
            f"pose: [{', '.join(repr(float(v)) for v in pose)}]\n"
            f"covariance: [{', '.join(repr(float(v)) for v in cov.ravel())}]\n")
    with atomic_write(path) as f:
        f.write(text.encode())
    return True


def load_pose(path) -> tuple[StoredPose | None, str]:
    """(the stored pose, "") or (None, why not)."""
    import yaml
    path = Path(path)
    if not path.is_file():
        return None, f"no persisted pose at {path}"
    try:
        doc = yaml.safe_load(path.read_text()) or {}
        pose = np.asarray(doc["pose"], dtype=float).reshape(3)
        cov = np.asarray(doc.get("covariance", np.zeros(9)), dtype=float).reshape(3, 3)
        stamp = float(doc.get("stamp", 0.0))
        frame_id = str(doc.get("frame_id", ""))
    except (OSError, ValueError, TypeError, KeyError, yaml.YAMLError) as exc:
        return None, f"persisted pose {path} unreadable ({exc})"
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
        return None, f"persisted pose {path} is not finite"
    return StoredPose(pose, cov, frame_id, stamp), ""
