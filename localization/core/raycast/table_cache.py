"""The range table's disk cache: one ``.npz`` per (map content, max range, heading bins, format).

Files are written atomically (``paths.atomic_write``) so a crash or a concurrent writer never
leaves half a table; a stale or unreadable file only costs a rebuild. Tables alive in this
process are shared by cache name: a second caster for the same map (a map message sent again,
another filter) reuses the table instead of reading a second copy.
"""
from __future__ import annotations

import json
import logging
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


def cache_file_name(occupancy_map: OccupancyMap, max_range: float, theta_bins: int) -> str:
    """The cache key as a file name: map content digest + max range + bins + format version."""
    return f"range_table_v{FORMAT_VERSION}_{occupancy_map.digest}_r{float(max_range):.9g}_k{int(theta_bins)}.npz"


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
            if meta != expected:
                log.warning("range table cache %s does not match this map/parameters: rebuilding", path)
                return None
            table = data["table"]
        if table.dtype != np.uint16 or table.shape != (expected["num_free"], theta_bins):
            raise ValueError(f"table has dtype {table.dtype} shape {table.shape}")
        return table
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("unreadable range table cache %s (%s): rebuilding", path, exc)
        return None


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
