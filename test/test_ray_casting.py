"""Ray casting: analytic distances in a hand-built corridor, and accuracy on the Stata basement."""
import numpy as np
import pytest
from helpers import corridor_map

from localization.core.geometry import compose
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast import DistanceTransformRayCaster, ExactRayCaster

CASTERS = [ExactRayCaster, DistanceTransformRayCaster]


@pytest.mark.parametrize("caster_cls", CASTERS)
@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), (3.0, -2.0, 0.7), (25.9, 48.5, 3.14)])
def test_corridor_analytic_ranges(caster_cls, origin):
    # Corridor (grid frame): free rows 11..49 (walls at rows 10 and 50), free columns 1..198.
    m = corridor_map(origin=origin)
    res = m.resolution
    # Sensor in the grid frame at column 100.5, row 30.5 (cell centre), expressed in the world.
    grid_pose = np.array([100.5 * res, 30.5 * res, 0.0])
    sensor = compose(np.array(origin), grid_pose)
    caster = caster_cls(m, max_range=20.0)
    angles = np.array([np.pi / 2, -np.pi / 2, 0.0, np.pi, np.pi / 4])
    r = caster.cast(sensor[None], angles)[0]
    up, down = (50 - 30.5) * res, (30.5 - 11) * res
    expected = [up, down, (199 - 100.5) * res, (100.5 - 1) * res, up * np.sqrt(2)]
    assert np.allclose(r, expected, atol=0.3 * res if caster_cls is ExactRayCaster else 0.6 * res)


@pytest.mark.parametrize("caster_cls", CASTERS)
def test_max_range_clip_and_blocked_start(caster_cls):
    m = corridor_map()
    caster = caster_cls(m, max_range=1.0)
    r = caster.cast(np.array([[5.0, 1.5, 0.0], [5.0, 0.52, 0.0], [-3.0, 0.0, 0.0]]), np.array([0.0]))
    assert r[0, 0] == pytest.approx(1.0)  # clipped: the corridor end is ~5 m away
    assert r[1, 0] == 0.0  # inside the wall row
    assert r[2, 0] == 0.0  # off the map


def test_distance_transform_caster_matches_exact_traversal_on_stata(maps_dir):
    m = OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")
    rng = np.random.default_rng(7)
    cells = m.free_cells[rng.integers(0, len(m.free_cells), 3000)]
    xy = m.grid_to_world(cells[:, ::-1]) + rng.uniform(-0.02, 0.02, (3000, 2))
    poses = np.column_stack([xy, rng.uniform(-np.pi, np.pi, 3000)])
    angles = np.linspace(-2.356, 2.356, 60)
    exact = ExactRayCaster(m, 10.08).cast(poses, angles)
    fast = DistanceTransformRayCaster(m, 10.08).cast(poses, angles)
    diff_cells = np.abs(exact - fast) / m.resolution
    median, p95 = np.median(diff_cells), np.percentile(diff_cells, 95)
    print(f"distance-transform vs exact on stata_basement: median {median:.3f} cells, p95 {p95:.3f} cells")
    assert median <= 0.5 and p95 <= 2.0
    assert np.all((exact >= 0) & (exact <= 10.08))
