"""Where maps, parameter files and caches are found (``localization.core.paths``)."""
from __future__ import annotations

from pathlib import Path

import pytest

from localization.core import paths
from localization.core.occupancy_map import MapError, load_map

REPO = Path(__file__).resolve().parents[1]


def test_a_bare_map_name_resolves_to_the_package_maps_first(monkeypatch, tmp_path):
    other = tmp_path / "maps"
    other.mkdir()
    (other / "stata_basement.yaml").write_text("image: x.png\n")
    monkeypatch.setenv("LOCALIZATION_MAPS_DIR", str(other))
    assert paths.resolve_map_path("stata_basement") == REPO / "maps" / "stata_basement.yaml"


def test_a_name_missing_from_the_package_is_looked_up_in_the_maps_dir(monkeypatch, tmp_path):
    (tmp_path / "garage.yaml").write_text("image: garage.png\nresolution: 0.05\norigin: [0, 0, 0]\n")
    monkeypatch.setenv("LOCALIZATION_MAPS_DIR", str(tmp_path))
    assert paths.resolve_map_path("garage") == tmp_path / "garage.yaml"


def test_every_shipped_map_loads_and_names_its_source():
    for name in ("stata_basement", "basement_fixed", "building_31"):
        m = load_map(name)
        assert m.source == REPO / "maps" / f"{name}.yaml" and len(m.free_cells) > 0


def test_bad_map_arguments_give_one_clear_error(tmp_path):
    with pytest.raises(MapError, match="not a map_server YAML"):
        load_map(REPO / "maps" / "basement_fixed.png")
    with pytest.raises(MapError, match="map not found"):
        load_map("no_such_map")


def test_parameter_files_by_name(tmp_path):
    assert paths.resolve_params_path("real_params") == REPO / "config" / "real_params.yaml"
    assert paths.resolve_params_path(tmp_path / "x.yaml") == tmp_path / "x.yaml"


def test_cache_dir_and_atomic_write(monkeypatch, tmp_path):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path / "c"))
    assert paths.cache_dir() == tmp_path / "c"
    target = tmp_path / "sub" / "f.bin"
    with paths.atomic_write(target) as f:
        f.write(b"abc")
    assert target.read_bytes() == b"abc"
    with pytest.raises(RuntimeError), paths.atomic_write(target) as f:
        f.write(b"partial")
        raise RuntimeError("crash mid-write")
    assert target.read_bytes() == b"abc" and not list(target.parent.glob("*.tmp"))
