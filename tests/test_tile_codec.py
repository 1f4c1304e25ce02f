"""The compact store voxel file (core/tile_codec.py): an exact round trip of what a map needs, on random
voxels and the edge cases (empty, one voxel, voxels on the tile's faces, negative and far tiles, tiles
wider than a byte), and every kind of damage refused with the file named."""

import numpy as np
import pytest

from evsemmap_warp.core.tile_codec import VoxelFileError, decode_voxels, encode_voxels, read_voxel_file, write_voxel_file


def _voxels(rng, count, tile, tile_voxels, classes=9):
    local = np.unique(rng.integers(0, tile_voxels, (count, 3)), axis=0)  # key order, no repeats
    index = local + np.asarray(tile) * tile_voxels
    rows = np.zeros((len(index), classes + 5))
    nonzero = rng.random((len(index), classes)) < 0.2  # sparse evidence, as label payloads give
    rows[:, :classes] = np.where(nonzero, rng.random((len(index), classes)) * 10 ** rng.uniform(-8, 6, (len(index), classes)), 0.0)
    rows[:, classes] = rng.random(len(index)) * 50
    rows[:, classes + 1] = rng.random(len(index))
    rows[:, classes + 2] = rng.integers(1, 2**40, len(index))  # counts stay exact
    rows[:, classes + 3] = rng.normal(0.0, 2.0, len(index))  # the weighted height sum, the one signed column
    rows[:, classes + 4] = rng.random(len(index)) < 0.9
    return index, rows


@pytest.mark.parametrize("tile,tile_voxels", [((0, 0, 0), 256), ((-3, 7, -1), 256), ((9765, 78125, 0), 256), ((-1, 2, 0), 300),
                                              ((2, -2, 1), 1)])
@pytest.mark.parametrize("count", [0, 1, 5000])
def test_round_trip_is_exact(tile, tile_voxels, count):
    rng = np.random.default_rng(count + tile_voxels)
    index, rows = _voxels(rng, count, tile, tile_voxels)
    data = encode_voxels(index, rows, tile, tile_voxels, {"store": "abc"})
    header, index_back, rows_back = decode_voxels(data, "x")
    np.testing.assert_array_equal(index_back, index)
    np.testing.assert_array_equal(rows_back, rows)  # bit for bit: float64 sums, counts, touched
    assert header["store"] == "abc" and header["voxels"] == len(index) and header["tile"] == list(tile)


def test_voxels_on_the_tile_faces_and_outside_it():
    tile_voxels = 256
    corners = np.array([[0, 0, 0], [0, 0, 255], [0, 255, 0], [255, 255, 255]]) + np.array([4, -5, 0]) * tile_voxels
    rows = np.ones((4, 13))
    _, index, back = decode_voxels(encode_voxels(corners, rows, (4, -5, 0), tile_voxels, {}), "x")
    np.testing.assert_array_equal(index, corners)
    with pytest.raises(ValueError, match="outside tile"):
        encode_voxels(corners + [256, 0, 0], rows, (4, -5, 0), tile_voxels, {})


def test_only_the_weighted_height_sum_may_be_negative():
    rng = np.random.default_rng(3)
    index, rows = _voxels(rng, 50, (0, 0, 0), 256, classes=3)
    rows[0, 6] = -0.25
    np.testing.assert_array_equal(decode_voxels(encode_voxels(index, rows, (0, 0, 0), 256, {}), "x")[2], rows)
    for column in range(6):  # evidence, weight sum, weighted-uncertainty sum, count
        bad = rows.copy()
        bad[0, column] = -1.0
        with pytest.raises(VoxelFileError, match="x: sums that are negative"):
            decode_voxels(encode_voxels(index, bad, (0, 0, 0), 256, {}), "x")


def test_a_small_file_for_sparse_sums():
    rng = np.random.default_rng(1)
    index, rows = _voxels(rng, 20000, (0, 0, 0), 256)
    rows[:, 10] = 0.0  # no uncertainty (label payloads)
    size = len(encode_voxels(index, rows, (0, 0, 0), 256, {})) / len(index)
    assert size < 48, size  # the store's budget per voxel (the npz map-file schema takes ~230)


def test_damage_is_refused_naming_the_file(tmp_path):
    rng = np.random.default_rng(2)
    index, rows = _voxels(rng, 300, (1, 1, 1), 256)
    path = write_voxel_file(tmp_path / "1_1_1.vox", index, rows, (1, 1, 1), 256, {"store": "s1"})
    data = path.read_bytes()
    cases = {
        "truncated": data[:-10],
        "cut in the header": data[:20],
        "other format": b"PK\x03\x04" + data[4:],
        "flipped payload byte": data[:-5] + bytes([data[-5] ^ 0xFF]) + data[-4:],
        "empty": b"",
    }
    for what, damaged in cases.items():
        (tmp_path / "bad.vox").write_bytes(damaged)
        with pytest.raises(VoxelFileError, match="bad.vox"):
            read_voxel_file(tmp_path / "bad.vox")
    header_text = data.replace(b'"voxels": 300', b'"voxels": 301')
    (tmp_path / "bad.vox").write_bytes(header_text)
    with pytest.raises(VoxelFileError, match="bad.vox"):
        read_voxel_file(tmp_path / "bad.vox")
    read_voxel_file(path, {"store": "s1", "tile": [1, 1, 1]})
    with pytest.raises(VoxelFileError, match="store is 's1', this store's is 's2'"):
        read_voxel_file(path, {"store": "s2"})
    with pytest.raises(VoxelFileError, match="cannot read"):
        read_voxel_file(tmp_path / "missing.vox")


@pytest.mark.parametrize("count", [0, 1, 5000])
def test_every_encoding_the_store_was_chosen_over_reads_back_bit_for_bit(count):
    """tools/bench_store_codec.py compares the store's encoding with the alternatives on equal terms: each
    must give back the same indices, float64 sums and touched flags."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    import bench_store_codec as bench

    rng = np.random.default_rng(count)
    index, rows = _voxels(rng, count, (-3, 7, 1), 256)
    tile = bench.Tile("t", index, rows, (-3, 7, 1), 256)
    sizes = {}
    for name, (encode, decode) in bench.encodings().items():
        data = encode(tile)
        assert tile.same(*decode(data, tile)), name
        sizes[name] = len(data)
    if count == 5000:
        ours = sizes["this store's .vox (zstd of the columns, checked on reading)"]
        assert ours < 0.5 * sizes["npz of the same arrays"]  # random sums: far less to gain than on a map's
