"""The reference track kept on disk, so a second replay of a bag, the demo and the tuner reuse it.

An entry is ``<cache dir>/reference/<key>.npz`` (``core.paths.cache_dir``, written atomically), its
key a digest of:

- what the track is built from, by content, never by path: a bag's file bytes (``bag_fingerprint``:
  every file of a rosbag2 folder, with their names inside it) and the topics and frames read from it,
  or the scans and odometry themselves (``inputs_fingerprint``);
- the map's content (its cells, resolution and origin);
- every argument of the yardstick (laser mount, start pose, matcher settings, range scale, wall
  depth, scan stamp convention, noise model, passes);
- the yardstick's code: the source of every module of the package it imports, its constants
  included (``code_version``), so a change to the method never serves an old track.

An entry that cannot be read is computed again (one log line); one that cannot be written is
reported (one log line) and the track returned all the same. The folder keeps the MAX_ENTRIES most
recently used entries (a hit refreshes an entry's time; storing one removes the oldest beyond).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np

from localization.core.paths import atomic_write, cache_dir
from localization.eval.reference.result import ReferenceTrack

FORMAT = 1  # of an entry's layout; part of the key
WHOLE_FILE_BYTES = 64 << 20  # files up to this size are hashed whole ...
SAMPLE_BYTES, SAMPLES = 1 << 20, 16  # ... larger ones by their size, first and last MiB and 16 MiB between
ARRAYS = ("t", "poses", "laser_poses", "matched", "information", "covariance", "std_along", "std_cross", "score",
          "usable", "accepted", "constrained", "good", "fit")
MAX_ENTRIES = 256  # entries kept (a few hundred kB each), the least recently used removed first
ROOT_MODULE = "localization.eval.reference.track"  # the computation (not its errors, plots or command line)


def reference_dir() -> Path:
    return cache_dir() / "reference"


def _file_digest(path: Path, h) -> None:
    size = path.stat().st_size
    h.update(f"{size}:".encode())
    with path.open("rb") as f:
        if size <= WHOLE_FILE_BYTES:
            h.update(f.read())
            return
        for offset in np.linspace(0, size - SAMPLE_BYTES, SAMPLES + 2).astype(np.int64):
            f.seek(int(offset))
            h.update(f.read(SAMPLE_BYTES))


def bag_fingerprint(bag_path) -> str | None:
    """Digest of a bag's content: the file, or every file of a rosbag2 folder with its name inside
    the folder (not the folder's own path); None when it cannot be read."""
    path = Path(bag_path)
    h = hashlib.blake2b(digest_size=20)
    try:
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            h.update(str(f.relative_to(path) if path.is_dir() else "").encode())
            _file_digest(f, h)
    except OSError:
        return None
    return h.hexdigest()


def _array_digest(h, a) -> None:
    a = np.ascontiguousarray(a)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())


def inputs_fingerprint(scans, odometry) -> str:
    """Digest of the scans (``ScanData``: ranges, angles, range limits, stamps, sweep timing) and the
    odometry (stamps, twists) a track is built from."""
    h = hashlib.blake2b(digest_size=20)
    fields = np.array([(s.stamp, s.angle_min, s.angle_max, s.angle_increment, s.range_min, s.range_max,
                        s.time_increment, s.scan_time) for s in scans], dtype=float).reshape(-1, 8)
    _array_digest(h, fields)
    for s in scans:
        _array_digest(h, np.asarray(s.ranges))
    _array_digest(h, np.asarray(odometry[0], dtype=float))
    _array_digest(h, np.asarray(odometry[1], dtype=float))
    return h.hexdigest()


def map_fingerprint(occupancy_map) -> str:
    h = hashlib.blake2b(digest_size=20)
    _array_digest(h, occupancy_map.data)
    h.update(repr((float(occupancy_map.resolution), tuple(float(v) for v in occupancy_map.origin))).encode())
    return h.hexdigest()


def _module_file(package_dir: Path, name: str) -> Path | None:
    rel = Path(*name.split(".")[1:])
    for candidate in (package_dir / rel / "__init__.py", (package_dir / rel).with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


_IMPORT = re.compile(rb"^[ \t]*(?:from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)|import[ \t]+([^\n]*))",
                     re.MULTILINE)


def _imported(source: bytes, name: str, is_package: bool) -> list[str]:
    """The ``localization`` modules a module's source imports (wherever the statement stands; a name
    imported from a package counts as a candidate submodule)."""
    package = name if is_package else name.rpartition(".")[0]
    out = []
    for base, names, plain in _IMPORT.findall(source):
        if plain:
            out += [n.split()[0] for n in plain.decode().split(",") if n.strip()]
            continue
        base = base.decode()
        level = len(base) - len(base.lstrip("."))
        if level:
            parts = package.split(".")
            base = ".".join(parts[:len(parts) - level + 1] + ([base[level:]] if base[level:] else []))
        words = names.decode().strip("()").replace("\n", " ").split(",")
        out += [base] + [f"{base}.{w.split()[0]}" for w in words if w.split() and w.split()[0].isidentifier()]
    return [m for m in out if m == "localization" or m.startswith("localization.")]


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """Digest of the source of every ``localization`` module the track's computation imports (transitively)."""
    package_dir = Path(__file__).resolve().parents[2]
    h = hashlib.blake2b(digest_size=20)
    seen: set[str] = set()
    todo = [ROOT_MODULE]
    files = {}
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = _module_file(package_dir, name)
        if path is None:
            continue
        source = path.read_bytes()
        files[name] = source
        todo += _imported(source, name, path.name == "__init__.py")
    for name in sorted(files):
        h.update(name.encode())
        h.update(files[name])
    return h.hexdigest()


def _plain(value):
    """JSON-ready form of an argument: dataclasses as dicts, arrays and tuples as lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {k: _plain(v) for k, v in dataclasses.asdict(value).items()}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return value


def reference_key(source: dict, occupancy_map, arguments: dict) -> str:
    """The cache key of a track built from ``source`` (fingerprints and what was read) on the map
    with the yardstick's ``arguments``."""
    text = json.dumps({"format": FORMAT, "source": _plain(source), "map": map_fingerprint(occupancy_map),
                       "arguments": _plain(arguments), "code": code_version()}, sort_keys=True)
    return hashlib.blake2b(text.encode(), digest_size=20).hexdigest()


def save(path: Path, ref: ReferenceTrack) -> None:
    arrays = {name: np.asarray(getattr(ref, name)) for name in ARRAYS if getattr(ref, name) is not None}
    meta = {"odometry": ref.odometry, "counts": ref.counts, "resolution": ref.resolution}
    with atomic_write(path) as f:
        np.savez(f, meta=np.array(json.dumps(meta)), **arrays)


def load(path: Path) -> ReferenceTrack:
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {name: z[name] for name in ARRAYS if name in z.files}
    return ReferenceTrack(**arrays, odometry=meta["odometry"], counts=meta["counts"],
                          resolution=float(meta["resolution"]))


def cached(key: str | None, compute, log=None) -> ReferenceTrack:
    """The track stored under ``key``, else ``compute()`` stored there (``key`` None: no cache)."""
    say = log or (lambda *_: None)
    if key is None:
        return compute()
    path = reference_dir() / f"{key}.npz"
    if path.is_file():
        try:
            ref = load(path)
            with contextlib.suppress(OSError):
                os.utime(path)  # recently used
            say(f"reference track from the cache ({path})")
            return ref
        except (OSError, ValueError, KeyError, TypeError) as exc:
            say(f"reference cache entry {path} unreadable ({exc}); computing the track again")
    ref = compute()
    try:
        save(path, ref)
        prune(path.parent)
    except OSError as exc:
        say(f"reference track not cached: cannot write {path} ({exc})")
    return ref


def prune(folder: Path, keep: int | None = None) -> None:
    """Remove all but the ``keep`` (MAX_ENTRIES) most recently used entries of ``folder``."""
    keep = MAX_ENTRIES if keep is None else keep
    entries = []
    for entry in folder.glob("*.npz"):
        with contextlib.suppress(OSError):  # another process may remove it meanwhile
            entries.append((entry.stat().st_mtime, entry))
    for _, entry in sorted(entries, reverse=True)[keep:]:
        with contextlib.suppress(OSError):
            entry.unlink()
