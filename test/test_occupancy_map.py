"""Map loading (map_server semantics, rotated origin) and world <-> grid transforms."""
import numpy as np
import pytest
from helpers import corridor_map, occupancy_grid_msg
from PIL import Image

from localization.core.occupancy_map import MapError, OccupancyMap, grid_from_image, occupancy_from_pixels


@pytest.fixture(scope="module")
def stata(maps_dir):
    return OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")


def test_stata_basement_loads_with_rotated_origin(stata):
    assert stata.data.shape == (1300, 1730)
    assert stata.resolution == pytest.approx(0.0504)
    assert stata.origin == pytest.approx((25.9, 48.5, 3.14))
    assert 250_000 < stata.free.sum() < 400_000  # ~310k free cells
    assert stata.occupied.sum() > 10_000


def test_world_grid_world_round_trip_with_rotated_origin(stata):
    rng = np.random.default_rng(0)
    cells = np.column_stack([rng.integers(0, stata.width, 1000), rng.integers(0, stata.height, 1000)])
    xy = stata.grid_to_world(cells)
    assert np.array_equal(stata.world_to_grid(xy), cells)
    # With yaw ~pi the image is flipped: larger column index -> smaller world x.
    a, b = stata.grid_to_world(np.array([[100, 100], [200, 100]]))
    assert b[0] < a[0] - 4.9
    # The origin is the corner of cell (0, 0).
    assert np.array_equal(stata.world_to_grid(np.array([[25.9 - 0.01, 48.5 - 0.001]])), [[0, 0]])


def test_row_zero_is_the_bottom_of_the_image(tmp_path):
    img = np.full((4, 3), 254, dtype=np.uint8)  # free
    img[0, :] = 0  # top image row occupied
    img[3, 0] = 205  # bottom-left unknown
    Image.fromarray(img).save(tmp_path / "m.png")
    (tmp_path / "m.yaml").write_text("image: m.png\nresolution: 0.1\norigin: [1.0, 2.0, 0.0]\nnegate: 0\n"
                                     "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    m = OccupancyMap.from_yaml(tmp_path / "m.yaml")
    assert m.data.shape == (4, 3)
    assert np.all(m.data[3] == 100)  # top image row = last grid row
    assert m.data[0, 0] == -1 and m.data[0, 1] == 0
    assert m.is_free(np.array([[1.15, 2.05]]))[0] and not m.is_free(np.array([[1.05, 2.05]]))[0]


def test_map_server_thresholds_and_negate():
    px = np.array([[0, 100, 205, 254, 255]], dtype=float)
    assert occupancy_from_pixels(px, False, 0.65, 0.196).tolist() == [[100, -1, -1, 0, 0]]
    assert occupancy_from_pixels(px, True, 0.65, 0.196).tolist() == [[0, -1, 100, 100, 100]]
    scaled = occupancy_from_pixels(px, False, 0.65, 0.196, "scale")
    assert scaled[0, 0] == 100 and 0 < scaled[0, 1] < 100 and scaled[0, 4] == 0


@pytest.mark.parametrize("channels", [0, 2, 3, 4])
@pytest.mark.parametrize("mode", ["trinary", "scale", "raw"])
@pytest.mark.parametrize("negate", [False, True])
def test_image_table_equals_the_float_pass(channels, mode, negate):
    """An 8-bit image through the table of its possible values gives map_server's float pass exactly
    (colour: the mean of the colour channels, alpha ignored)."""
    rng = np.random.default_rng(channels)
    shape = (37, 41) if channels == 0 else (37, 41, channels)
    pixels = rng.integers(0, 256, shape, dtype=np.uint8)
    pixels.reshape(-1)[:256] = np.arange(256)  # every grey level
    if channels == 0:
        grey = pixels.astype(float)
    else:
        grey = pixels[..., :3].mean(axis=2) if channels >= 3 else pixels[..., 0].astype(float)
    expected = occupancy_from_pixels(grey, negate, 0.65, 0.196, mode)
    got = grid_from_image(pixels, negate, 0.65, 0.196, mode)
    assert got.dtype == expected.dtype == np.int8
    np.testing.assert_array_equal(got, expected)
    assert len(np.unique(got)) > 2  # occupied, free and unknown (scale: the levels between) all present
    # a 16-bit image takes the float pass
    np.testing.assert_array_equal(grid_from_image(pixels.astype(np.uint16), negate, 0.65, 0.196, mode), expected)


def test_from_msg_matches_from_yaml(stata):
    again = OccupancyMap.from_msg(occupancy_grid_msg(stata))
    assert np.array_equal(again.data, stata.data)
    assert again.origin == pytest.approx(stata.origin, abs=1e-9)
    assert again.digest == stata.digest


@pytest.mark.parametrize("change, message", [
    (dict(resolution=0.0), "resolution"),
    (dict(data_len=5), "width x height"),
    (dict(width=0), "no cells"),
])
def test_inconsistent_maps_raise_clear_errors(change, message):
    msg = occupancy_grid_msg(corridor_map())
    if "resolution" in change:
        msg.info.resolution = change["resolution"]
    if "data_len" in change:
        msg.data = msg.data[:change["data_len"]]
    if "width" in change:
        msg.info.width = 0
    with pytest.raises(MapError, match=message):
        OccupancyMap.from_msg(msg)


def test_unreadable_yaml_raises(tmp_path):
    with pytest.raises(MapError):
        OccupancyMap.from_yaml(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("image: nothere.png\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapError, match="image"):
        OccupancyMap.from_yaml(tmp_path / "bad.yaml")


@pytest.mark.parametrize("radius", [0.0, 0.05, 0.125, 0.30])
def test_near_obstacle_equals_the_distance_threshold(maps_dir, radius):
    m = OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")
    np.testing.assert_array_equal(m.near_obstacle(radius), m.distance_to_obstacle() <= radius + 1e-12)
