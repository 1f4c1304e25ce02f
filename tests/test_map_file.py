"""Map files: exact round trips and clear errors for files that are not what they claim."""

import json
import zipfile

import numpy as np
import pytest

from evsemmap_warp.config import legacy_flat_dict, load_config
from evsemmap_warp.core.map_file import FORMAT_VERSION, MapFileError, read_map_arrays
from evsemmap_warp.core.mapper import Mapper, load_map, save_map

from conftest import REPO


@pytest.fixture
def small_map(device):
    cfg = load_config([REPO / "configs/presets/rellis3d.yaml"], method="ebs").mapping
    mapper = Mapper(cfg, 9, class_names=[f"c{i}" for i in range(9)], device=device)
    rng = np.random.default_rng(0)
    for _ in range(3):
        pts = rng.uniform(-5, 5, (2000, 3))
        alpha = 1 + rng.gamma(0.3, 30, (2000, 9))
        mapper.integrate(pts, alpha, payload_type="alpha")
    return mapper


def test_round_trip_is_exact(tmp_path, small_map, device):
    path = save_map(tmp_path / "m.npz", small_map)
    first, meta = read_map_arrays(path)
    loaded = load_map(path, device=device)
    again = save_map(tmp_path / "again.npz", loaded)
    second, meta2 = read_map_arrays(again)
    assert first.keys() == second.keys() and meta == meta2
    for name in first:
        np.testing.assert_array_equal(first[name], second[name], err_msg=name)
    assert meta["format_version"] == FORMAT_VERSION and meta["method"] == "ebs" and meta["mapping"]["gamma"] == 10.0
    assert first["centers"].dtype == np.float64 and first["alpha"].dtype == np.float64 and first["evidence"].dtype == np.float64 and first["state"].dtype == np.int8
    np.testing.assert_allclose(first["centers"], (first["voxel_index"] + 0.5) * 0.2)
    q = np.random.default_rng(1).uniform(-5, 5, (500, 3))
    a, b = small_map.query(q), loaded.query(q)
    np.testing.assert_array_equal(a.label, b.label)
    np.testing.assert_array_equal(a.variance, b.variance)


def test_a_map_written_before_the_mode_sections_loads_silently(tmp_path, small_map, capsys):
    # map files record MappingConfig.as_dict(); before the sections it was flat, with -1 for "none"
    path = save_map(tmp_path / "m.npz", small_map)
    with np.load(path) as arrays:
        data = dict(arrays)
    meta = json.loads(str(data["meta"]))
    assert meta["mapping"]["sbki"]["max_range_m"] is None and "block_depth" not in meta["mapping"]
    meta["mapping"] = legacy_flat_dict(meta["mapping"])
    data["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "old.npz", **data)
    capsys.readouterr()
    old = load_map(tmp_path / "old.npz")
    assert old.config == small_map.config and old.config.sbki.max_range_m is None and old.config.release.ds_multiplier is None
    assert old.voxels().arrays.rows().tobytes() == small_map.voxels().arrays.rows().tobytes()
    assert "deprecated" not in capsys.readouterr().err

def test_saving_to_a_name_without_npz_suffix_keeps_the_name(tmp_path, small_map):
    path = save_map(tmp_path / "map.evsem", small_map)
    assert path.exists() and not (tmp_path / "map.evsem.npz").exists()


def test_truncated_file(tmp_path, small_map):
    path = save_map(tmp_path / "m.npz", small_map)
    data = path.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFileError, match="corrupt or truncated") as err:
        load_map(cut)
    assert "cut.npz" in str(err.value)


def test_not_a_map_file(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"definitely not a zip")
    with pytest.raises(MapFileError, match="corrupt or truncated"):
        load_map(junk)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(MapFileError, match="not an evsemmap map file"):
        load_map(other)
    with pytest.raises(MapFileError, match="no such map file"):
        load_map(tmp_path / "missing.npz")


def _rewrite(path, out, **changes):
    with np.load(path, allow_pickle=False) as d:
        arrays = {k: d[k] for k in d.files}
    arrays.update(changes)
    np.savez(out, **arrays)
    return out


def test_other_format_version_is_refused(tmp_path, small_map):
    path = save_map(tmp_path / "m.npz", small_map)
    meta = json.loads(str(np.load(path)["meta"]))
    meta["format_version"] = 99
    bad = _rewrite(path, tmp_path / "v99.npz", meta=np.array(json.dumps(meta)), format_version=np.int64(99))
    with pytest.raises(MapFileError, match="format version 99.*reads versions 1, 2"):
        load_map(bad)


def test_inconsistent_shapes_and_pickled_objects_are_refused(tmp_path, small_map):
    path = save_map(tmp_path / "m.npz", small_map)
    bad = _rewrite(path, tmp_path / "shape.npz", alpha=np.zeros((3, 9), np.float32))
    with pytest.raises(MapFileError, match="field 'alpha' has shape"):
        load_map(bad)
    pickled = _rewrite(path, tmp_path / "pickle.npz", meta=np.array([{"a": 1}], dtype=object))
    with pytest.raises(MapFileError, match="holds Python objects"):
        load_map(pickled)
    with zipfile.ZipFile(path) as z:
        assert all(not n.endswith(".pkl") for n in z.namelist())


def test_version_1_files_still_load(tmp_path, small_map):
    """The previous format: float32 values, int32 indices, no origin (the map sat at 0)."""
    path = save_map(tmp_path / "m.npz", small_map)
    with np.load(path, allow_pickle=False) as d:
        arrays = {k: d[k] for k in d.files if k != "origin"}
    meta = json.loads(str(arrays["meta"])) | {"format_version": 1}
    arrays |= {"meta": np.array(json.dumps(meta)), "format_version": np.int64(1), "voxel_index": arrays["voxel_index"].astype(np.int32)}
    for name in ("alpha", "evidence", "variance", "weight_sum", "weighted_uncertainty_sum"):
        arrays[name] = arrays[name].astype(np.float32)
    old = tmp_path / "v1.npz"
    np.savez(old, **arrays)
    loaded = load_map(old)
    (a, sa), (b, sb) = small_map.voxels(), loaded.voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-6)
    assert (sa.label != sb.label).sum() <= 2  # float32 rounding may decide a near-tie
