"""The reference track's disk cache: a second call with the same bag content, map and arguments
returns the stored track (equal arrays, the bag not read again), a copy of the bag elsewhere hits it,
and a changed argument, map cell or bag byte misses it; unreadable entries are recomputed."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from localization.core.occupancy_map import OccupancyMap, load_map
from localization.core.scan import ScanData
from localization.eval.datasets import real_bag, real_bag_path
from localization.eval.reference import cache as C
from localization.eval.reference import reference_for_bag, track
from localization.eval.reference.result import ReferenceTrack


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "reference"


def _assert_equal_tracks(a: ReferenceTrack, b: ReferenceTrack):
    for name in C.ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    assert a.odometry == b.odometry and a.counts == b.counts and a.resolution == b.resolution


class _Spy:
    """Stands in for the computation: counts calls and returns a given track."""

    def __init__(self, ref):
        self.ref, self.calls = ref, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return self.ref


def test_a_second_replay_of_a_bag_reuses_its_reference_track(cache_dir, tmp_path, monkeypatch):
    rb = real_bag("bag3")
    bag = real_bag_path(rb.name)
    m = load_map(rb.map)
    kw = dict(odom_topic=rb.odom_topic, initial_pose=rb.start, scan_stamp=rb.scan_stamp)
    lines = []
    first = reference_for_bag(bag, m, rb.scan_topic, (0.275, 0.0, 0.0), **kw, log=lines.append)
    assert len(list(cache_dir.glob("*.npz"))) == 1 and not any("cache" in s for s in lines)
    spy = _Spy(first)
    monkeypatch.setattr(track, "_read_and_build", spy)
    second = reference_for_bag(bag, m, rb.scan_topic, (0.275, 0.0, 0.0), **kw, log=lines.append)
    assert spy.calls == 0 and any("from the cache" in s for s in lines)
    _assert_equal_tracks(first, second)
    # the key is the bag's content, not its path
    copy = tmp_path / "renamed.bag"
    shutil.copyfile(bag, copy)
    _assert_equal_tracks(first, reference_for_bag(copy, m, rb.scan_topic, (0.275, 0.0, 0.0), **kw))
    assert spy.calls == 0
    # any argument of the yardstick, the topics, the map or the bag's bytes changed: a miss
    reference_for_bag(bag, m, rb.scan_topic, (0.275, 0.0, 0.0), **kw, wall_depth=0.01)
    assert spy.calls == 1
    reference_for_bag(bag, m, rb.scan_topic, (0.28, 0.0, 0.0), **kw)
    assert spy.calls == 2
    reference_for_bag(bag, m, rb.scan_topic, (0.275, 0.0, 0.0), **{**kw, "odom_topic": "/odom"})
    assert spy.calls == 3
    data = m.data.copy()
    data[0, 0] = 100 if data[0, 0] != 100 else 0
    reference_for_bag(bag, OccupancyMap(data, m.resolution, m.origin), rb.scan_topic, (0.275, 0.0, 0.0), **kw)
    assert spy.calls == 4
    raw = bytearray(copy.read_bytes())
    raw[len(raw) // 2] ^= 1
    copy.write_bytes(bytes(raw))
    reference_for_bag(copy, m, rb.scan_topic, (0.275, 0.0, 0.0), **kw)
    assert spy.calls == 5
    # without the cache: always computed
    reference_for_bag(bag, m, rb.scan_topic, (0.275, 0.0, 0.0), **kw, cache=False)
    assert spy.calls == 6


def _tiny_track(K=4) -> ReferenceTrack:
    rng = np.random.default_rng(1)
    return ReferenceTrack(t=np.arange(K, dtype=float), poses=rng.random((K, 3)), laser_poses=rng.random((K, 3)),
                          matched=np.where(np.arange(K)[:, None] == 1, np.nan, rng.random((K, 3))),
                          information=rng.random((K, 3, 3)), covariance=rng.random((K, 3, 3)),
                          std_along=rng.random(K), std_cross=rng.random(K), score=rng.random(K),
                          usable=np.array([True, False, True, True][:K]), accepted=np.ones(K, dtype=bool),
                          constrained=np.ones((K, 5), dtype=bool), good=np.ones(K, dtype=bool),
                          odometry={"speed_scale": 1.0 / 3.0, "noise_scales": {"match": 1.25}},
                          counts={"scans": K, "start": "given start pose"}, resolution=0.05, fit=None)


def _scans(n=5, value=2.0):
    return [ScanData(0.025 * k, np.full(30, value), -1.0, 1.0, 2.0 / 29, 0.1, 10.0) for k in range(n)]


def test_build_reference_is_keyed_by_the_scans_and_odometry_content(cache_dir, monkeypatch):
    """The tuner's path (scans in memory): the same content hits, a changed range, stamp or argument misses."""
    spy = _Spy(_tiny_track())
    monkeypatch.setattr(track, "_build", spy)
    m = OccupancyMap(np.zeros((20, 20), dtype=np.int8), 0.05, (0.0, 0.0, 0.0))
    odo = (np.arange(10) * 0.02, np.zeros((10, 3)))
    got = track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, initial_pose=(0.5, 0.5, 0.0))
    _assert_equal_tracks(got, spy.ref)
    got = track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, initial_pose=np.array([0.5, 0.5, 0.0]))
    assert spy.calls == 1  # a hit, read back from disk equal to what was stored
    _assert_equal_tracks(got, spy.ref)
    scans = _scans()
    scans[3].ranges[7] = 2.5
    track.build_reference(scans, m, (0.1, 0.0, 0.0), odo, initial_pose=(0.5, 0.5, 0.0))
    assert spy.calls == 2
    track.build_reference(_scans(), m, (0.1, 0.0, 0.0), (odo[0] + 0.001, odo[1]), initial_pose=(0.5, 0.5, 0.0))
    assert spy.calls == 3
    track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, initial_pose=(0.5, 0.5, 0.0), range_scale=0.98)
    assert spy.calls == 4
    track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, initial_pose=(0.5, 0.5, 0.0), second_pass=False)
    assert spy.calls == 5
    track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, initial_pose=(0.5, 0.5, 0.0), range_scale=0.98)
    assert spy.calls == 5


def test_an_unreadable_entry_is_computed_again_and_an_unwritable_cache_is_reported(cache_dir, monkeypatch):
    spy = _Spy(_tiny_track())
    monkeypatch.setattr(track, "_build", spy)
    m = OccupancyMap(np.zeros((20, 20), dtype=np.int8), 0.05, (0.0, 0.0, 0.0))
    odo = (np.arange(10) * 0.02, np.zeros((10, 3)))
    track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo)
    (entry,) = cache_dir.glob("*.npz")
    entry.write_bytes(b"not an npz")
    lines = []
    _assert_equal_tracks(track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, log=lines.append), spy.ref)
    assert spy.calls == 2 and any("unreadable" in s for s in lines)
    track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo)
    assert spy.calls == 2  # rewritten whole
    entry.unlink()

    def full(*_):
        raise OSError("No space left on device")
    monkeypatch.setattr(C, "save", full)
    lines = []
    _assert_equal_tracks(track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, log=lines.append), spy.ref)
    assert spy.calls == 3 and any("not cached" in s and "No space" in s for s in lines)


def test_the_code_version_covers_the_yardstick_and_what_it_imports():
    src = (b"from localization.core.matching import kernels as K\n"
           b"from . import cache as C\n"
           b"from .errors import (\n    best_lag,\n    track_errors,\n)\n"
           b"    import localization.bags, numpy as np\n"
           b'"""from localization.tools import demo"""\n')
    got = C._imported(src, "localization.eval.reference.track", is_package=False)
    for name in ("localization.core.matching", "localization.core.matching.kernels", "localization.eval.reference",
                 "localization.eval.reference.cache", "localization.eval.reference.errors.track_errors",
                 "localization.bags"):
        assert name in got, (name, got)
    assert "numpy" not in got
    assert len(C.code_version()) == 40 and C.code_version() == C.code_version()


def test_the_cache_keeps_the_most_recently_used_entries(cache_dir, monkeypatch):
    import os
    spy = _Spy(_tiny_track())
    monkeypatch.setattr(track, "_build", spy)
    monkeypatch.setattr(C, "MAX_ENTRIES", 2)
    m = OccupancyMap(np.zeros((20, 20), dtype=np.int8), 0.05, (0.0, 0.0, 0.0))
    odo = (np.arange(10) * 0.02, np.zeros((10, 3)))

    def build(scale):
        return track.build_reference(_scans(), m, (0.1, 0.0, 0.0), odo, range_scale=scale)
    build(1.0)
    build(0.99)
    for i, entry in enumerate(sorted(cache_dir.glob("*.npz"), key=lambda e: e.stat().st_mtime)):
        os.utime(entry, (1e9 + i, 1e9 + i))  # distinct times, 1.0's entry the older
    build(1.0)  # a hit: now the most recently used
    assert spy.calls == 2
    build(0.98)  # a third entry: 0.99's, the least recently used, goes
    assert len(list(cache_dir.glob("*.npz"))) == 2
    build(1.0)
    assert spy.calls == 3
    build(0.99)
    assert spy.calls == 4
