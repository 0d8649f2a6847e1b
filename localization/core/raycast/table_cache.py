"""The range table's disk cache: one ``.npz`` per (map content, max range, heading bins, format).
The map's ``digest`` and the max range are quantized, so one map has one file whether it was read
from its YAML or received as a nav_msgs/OccupancyGrid (float32 resolution).

Files are written atomically (``paths.atomic_write``) so a crash or a concurrent writer never
leaves half a table; a stale or unreadable file only costs a rebuild. Tables alive in this
process are shared by cache name: a second caster for the same map (a map message sent again,
another filter) reuses the table instead of reading a second copy. A cached table is mapped from its file
(copy on write), not read: a process holds in memory only the rows its particles reach, and the start
does not wait for the whole file.
"""
from __future__ import annotations

import json
import logging
import math
import mmap
import struct
import weakref
import zipfile
from pathlib import Path

import numpy as np

from localization.core.occupancy_map import OccupancyMap
from localization.core.paths import atomic_write
from localization.core.raycast.kernels import TABLE_MAX_UNITS

FORMAT_VERSION = 2  # 2: tables of the sphere-tracing build before the diagonal fix are not reused

log = logging.getLogger(__name__)

LIVE_TABLES: "weakref.WeakValueDictionary[str, np.ndarray]" = weakref.WeakValueDictionary()


RANGE_DECIMALS = 6  # the max range (m) names a cache file rounded to 1e-6 m
META_RTOL = 1e-6  # a cached table's float meta data (max range, units per cell) match within this


def cache_file_name(occupancy_map: OccupancyMap, max_range: float, theta_bins: int) -> str:
    """The cache key as a file name: map content digest + max range (rounded to RANGE_DECIMALS,
    so a max range computed from a float32 resolution names the same file) + bins + format version."""
    r = round(float(max_range), RANGE_DECIMALS)
    return f"range_table_v{FORMAT_VERSION}_{occupancy_map.digest}_r{r:.9g}_k{int(theta_bins)}.npz"


def meta_matches(meta: dict, expected: dict) -> bool:
    """The same keys and values; floats within META_RTOL (the same map as YAML or as a message)."""
    if not isinstance(meta, dict) or set(meta) != set(expected):
        return False
    for key, want in expected.items():
        got = meta[key]
        if isinstance(want, float) and isinstance(got, (int, float)) and not isinstance(got, bool):
            if not math.isclose(got, want, rel_tol=META_RTOL):
                return False
        elif got != want:
            return False
    return True


def table_meta(occupancy_map: OccupancyMap, max_range: float, theta_bins: int) -> dict:
    return {"format_version": FORMAT_VERSION, "map_digest": occupancy_map.digest, "max_range": float(max_range),
            "theta_bins": int(theta_bins), "num_free": int(np.count_nonzero(occupancy_map.free)),
            "units_per_cell": TABLE_MAX_UNITS / (float(max_range) / occupancy_map.resolution)}


def load_table(path: Path, occupancy_map: OccupancyMap, max_range: float, theta_bins: int) -> np.ndarray | None:
    """The cached table, or None when missing, stale or unreadable."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            expected = table_meta(occupancy_map, max_range, theta_bins)
            if not meta_matches(meta, expected):
                log.warning("range table cache %s does not match this map/parameters: rebuilding", path)
                return None
            table = mapped_member(path, data.zip.getinfo("table.npy"))
            if table is None:
                table = data["table"]
        if table.dtype != np.uint16 or table.shape != (expected["num_free"], theta_bins):
            raise ValueError(f"table has dtype {table.dtype} shape {table.shape}")
        return table
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("unreadable range table cache %s (%s): rebuilding", path, exc)
        return None


ZIP_LOCAL_HEADER = struct.Struct("<4s5H3I2H")  # a zip member's local header (30 bytes); the last two: name, extra


def mapped_member(path: Path, info: zipfile.ZipInfo) -> np.ndarray | None:
    """The ``.npy`` array stored uncompressed as the member ``info`` of the zip at ``path``, mapped copy on
    write (an ordinary writable ndarray whose pages are read from the file when first touched; the file's
    pages are asked for ahead, in the background); None when the member is compressed or its header is
    not a plain array's."""
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    with open(path, "rb") as f:
        f.seek(info.header_offset)
        *_, name_len, extra_len = ZIP_LOCAL_HEADER.unpack(f.read(ZIP_LOCAL_HEADER.size))
        start = info.header_offset + ZIP_LOCAL_HEADER.size + name_len + extra_len  # the member's bytes
        f.seek(start)
        version = np.lib.format.read_magic(f)
        if version not in ((1, 0), (2, 0)):
            return None
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(f)
        offset = f.tell()
    if fortran or dtype.hasobject or offset + math.prod(shape) * dtype.itemsize > start + info.file_size:
        return None
    mapped = np.memmap(path, dtype=dtype, mode="c", shape=shape, offset=offset)
    if hasattr(mmap, "MADV_WILLNEED"):
        mapped._mmap.madvise(mmap.MADV_WILLNEED)
    return np.asarray(mapped)


WRITE_CHUNK_BYTES = 1 << 20  # the table goes to disk 1 MiB at a time (np.savez copies 16 MiB pieces)


def save_table(path: Path, table: np.ndarray, meta: dict) -> None:
    """Write the table and its meta data atomically, as the ``.npz`` that ``np.savez`` writes (an
    uncompressed zip of ``table.npy`` and ``meta.npy``; ``np.load`` reads it), but streaming the
    table's bytes without a copy."""
    table = np.ascontiguousarray(table)
    with atomic_write(path) as f, zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        with zf.open("table.npy", "w", force_zip64=True) as out:
            np.lib.format.write_array_header_1_0(out, np.lib.format.header_data_from_array_1_0(table))
            data = memoryview(table).cast("B")
            for start in range(0, len(data), WRITE_CHUNK_BYTES):
                out.write(data[start:start + WRITE_CHUNK_BYTES])
        with zf.open("meta.npy", "w") as out:
            np.lib.format.write_array(out, np.array(json.dumps(meta, sort_keys=True)))
