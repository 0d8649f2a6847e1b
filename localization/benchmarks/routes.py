"""Other maps: a closed route built from the map's free space (no hand-picked waypoints), for the
benchmarks' drives in buildings other than the Stata basement (``auto_loop``)."""
from __future__ import annotations

import math

import numpy as np

from localization.sim import clearance_grid


def _clearance_graph(clear: np.ndarray, keep: np.ndarray, cell: float, penalty: np.ndarray | None = None):
    """8-connected graph of the ``keep`` cells; an edge costs its length × (1 + 1 m / clearance)
    (so shortest paths keep to the corridors' centre lines), × 50 where ``penalty`` is set."""
    from scipy.sparse import coo_matrix
    rows, cols = np.nonzero(keep)
    idx = -np.ones(keep.shape, dtype=np.int64)
    idx[rows, cols] = np.arange(len(rows))
    h, w = keep.shape
    src, dst, cost = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r2, c2 = rows + dr, cols + dc
        ok = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
        ok[ok] &= keep[r2[ok], c2[ok]]
        ra, ca, rb, cb = rows[ok], cols[ok], r2[ok], c2[ok]
        wt = math.hypot(dr, dc) * cell * (1.0 + 2.0 / (clear[ra, ca] + clear[rb, cb]))
        if penalty is not None:
            wt = wt * np.where(penalty[ra, ca] | penalty[rb, cb], 50.0, 1.0)
        src.append(idx[ra, ca])
        dst.append(idx[rb, cb])
        cost.append(wt)
    a, b, wt = np.concatenate(src), np.concatenate(dst), np.concatenate(cost)
    n = len(rows)
    graph = coo_matrix((np.concatenate([wt, wt]), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(n, n))
    return graph.tocsr(), rows, cols


def _back_path(pred: np.ndarray, src: int, dst: int) -> list:
    out = [dst]
    while out[-1] != src:
        out.append(int(pred[out[-1]]))
    return out[::-1]


def _cut_spikes(pts: np.ndarray, close: float = 0.6, min_arc: float = 2.0) -> np.ndarray:
    """Remove out-and-back detours from a closed polyline: a stretch longer than ``min_arc`` (and
    shorter than half the loop) whose two ends are within ``close`` of each other."""
    changed = True
    while changed:
        changed = False
        n = len(pts)
        seg = np.hypot(*np.diff(pts, axis=0, append=pts[:1]).T)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        total = s[-1]
        for i in range(n):
            arc = (s[np.arange(n)] - s[i]) % total  # arc length from i forward to every j
            d = np.hypot(*(pts - pts[i]).T)
            cand = np.nonzero((d < close) & (arc > min_arc) & (arc < 0.5 * total))[0]
            if cand.size:
                j = int(cand[np.argmax(arc[cand])])
                keep = np.ones(n, dtype=bool)
                k = (i + 1) % n
                while k != j:
                    keep[k] = False
                    k = (k + 1) % n
                pts = pts[keep]
                changed = True
                break
    return pts


def enclosed(occ) -> np.ndarray:
    """Cells inside the building: a ray from the cell in at most one of 8 directions (rows,
    columns, diagonals) leaves the map without meeting a wall (walls thickened by one cell). Maps
    that mark the outside of the building free (``building_31``) otherwise invite routes outside."""
    from scipy import ndimage
    wall = ndimage.binary_dilation(~occ.free, structure=np.ones((3, 3)))
    h, w = wall.shape
    escapes = np.zeros(wall.shape, dtype=np.int8)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == dc == 0:
                continue
            if dr == 0:  # along the row: cumulative "a wall so far" from the far end
                src = wall if dc < 0 else wall[:, ::-1]
                hit = np.logical_or.accumulate(src, axis=1)
                hit = hit if dc < 0 else hit[:, ::-1]
            else:
                hit = np.zeros_like(wall)
                order = range(h) if dr < 0 else range(h - 1, -1, -1)
                prev = np.zeros(w, dtype=bool)  # beyond the edge: no wall
                for r in order:
                    shifted = np.zeros(w, dtype=bool)
                    if dc > 0:
                        shifted[:-1] = prev[1:]
                    elif dc < 0:
                        shifted[1:] = prev[:-1]
                    else:
                        shifted = prev
                    hit[r] = wall[r] | shifted
                    prev = hit[r]
            escapes += ~hit
    return escapes <= 1


def auto_loop(occ, path_clearance: float = 0.3, end_clearance: float = 0.4, spacing: float = 1.0,
              step: int = 2) -> np.ndarray:
    """A closed route (waypoints ~``spacing`` m apart) through ``occ``'s free space, built from its
    clearance grid (``localization.sim.clearance_grid``) alone. On the cells inside the building
    (``enclosed``) with clearance >= ``path_clearance`` (the largest connected piece, every
    ``step``-th cell): the two cells of clearance >= ``end_clearance`` farthest apart along
    corridors, A and B; a clearance-weighted shortest path A -> B, then B -> A again avoiding
    (x 50 cost) 1.2 m around the first; the two make a loop, with out-and-back detours cut away."""
    from scipy import ndimage
    from scipy.sparse.csgraph import dijkstra
    cell = occ.resolution * step
    clear = clearance_grid(occ)[::step, ::step]
    nav = (clear >= path_clearance) & enclosed(occ)[::step, ::step]
    lab, n = ndimage.label(nav, structure=np.ones((3, 3)))
    if n == 0:
        raise ValueError(f"no free space with clearance >= {path_clearance} m in map {occ.source}")
    keep = lab == 1 + int(np.argmax(ndimage.sum(nav, lab, range(1, n + 1))))
    graph, rows, cols = _clearance_graph(clear, keep, cell)
    wide = clear[rows, cols] >= end_clearance
    seed = int(np.argmax(clear[rows, cols]))
    dist = dijkstra(graph, indices=seed)
    a = int(np.argmax(np.where(wide & np.isfinite(dist), dist, -1.0)))
    dist, pred = dijkstra(graph, indices=a, return_predecessors=True)
    b = int(np.argmax(np.where(wide & np.isfinite(dist), dist, -1.0)))
    first = _back_path(pred, a, b)
    mark = np.zeros_like(keep)
    mark[rows[first], cols[first]] = True
    penalty = ndimage.distance_transform_edt(~mark) * cell < 1.2
    graph2, _, _ = _clearance_graph(clear, keep, cell, penalty)
    _, pred2 = dijkstra(graph2, indices=b, return_predecessors=True)
    second = _back_path(pred2, b, a)
    cells = first + second[1:-1]
    colrow = np.stack([cols[cells], rows[cells]], axis=1) * step + (step - 1) / 2.0
    pts = _cut_spikes(occ.grid_to_world(colrow))
    # waypoints every ~spacing metres of arc
    seg = np.hypot(*np.diff(pts, axis=0, append=pts[:1]).T)
    s = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    n_wp = max(4, int(round((s[-1] + seg[-1]) / spacing)))
    picks = np.searchsorted(s, np.arange(n_wp) * (s[-1] + seg[-1]) / n_wp)
    return np.round(pts[np.unique(np.clip(picks, 0, len(pts) - 1))], 3)
