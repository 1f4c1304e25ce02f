"""Map files: exact round trips and clear errors for files that are not what they claim."""

import json

import numpy as np
import pytest

from evsemmap_warp.config import load_config
from evsemmap_warp.core.map_file import FORMAT_VERSION, MAGIC, MapFileError, read_map_file
from evsemmap_warp.core.mapper import read_map_arrays
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


def test_saving_to_a_name_without_npz_suffix_keeps_the_name(tmp_path, small_map):
    path = save_map(tmp_path / "map.evsem", small_map)
    assert path.exists() and not (tmp_path / "map.evsem.npz").exists()


def test_voxels_is_a_named_result_that_unpacks(small_map):
    voxels = small_map.voxels()
    arrays, summary = voxels
    assert arrays is voxels.arrays is voxels[0] and summary is voxels.summary is voxels[1]
    assert len(voxels.summary.label) == len(voxels.arrays.index) == small_map.voxel_count


def test_truncated_file(tmp_path, small_map):
    data = save_map(tmp_path / "m.npz", small_map).read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFileError, match="truncated") as err:
        load_map(cut)
    assert "cut.npz" in str(err.value)


def test_not_a_map_file(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"definitely not a zip")
    with pytest.raises(MapFileError, match=r"junk.npz: not an evsemmap map file \(a version-3 map file begins with EVSMMAP3\)"):
        load_map(junk)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3), format_version=np.zeros(10**5, np.int64))  # no map's version, and too big to be one
    with pytest.raises(MapFileError, match="not an evsemmap map file"):
        load_map(other)
    with pytest.raises(MapFileError, match="no such map file"):
        load_map(tmp_path / "missing.npz")


@pytest.mark.parametrize("version", [1, 2])
def test_an_npz_map_of_an_earlier_version_is_refused_naming_it(tmp_path, version):
    """Versions 1 and 2 (one npz of every array) were written only by this repository's earlier versions."""
    old = tmp_path / f"v{version}.npz"
    np.savez(old, format_version=np.int64(version), meta=np.array("{}"), evidence=np.zeros((1, 3)))
    with pytest.raises(MapFileError, match=rf"v{version}.npz: map format version {version}; this evsemmap_warp reads version 3 only"):
        load_map(old)


def test_another_format_version_in_the_header_is_refused(tmp_path, tiny_map_file):
    head, _ = _parts(tiny_map_file)
    bad = _rewrite_v3(tiny_map_file, tmp_path / "v99.npz", {"format_version": 99, "meta": head["meta"] | {"format_version": 99}})
    with pytest.raises(MapFileError, match=r"v99.npz: map format version 99; this evsemmap_warp reads version 3 only"):
        load_map(bad)


# ------------------------------------------------------------------------------------- version 3
def test_a_round_trip_gives_the_same_bytes_and_sums(tmp_path, small_map):
    path = save_map(tmp_path / "m.npz", small_map)
    assert path.read_bytes()[:len(MAGIC)] == MAGIC and FORMAT_VERSION == 3
    contents = read_map_file(path)
    assert contents.alpha is None and contents.centers is None  # the read-out is derived only when asked for
    arrays = small_map.voxels().arrays
    np.testing.assert_array_equal(contents.index, arrays.index)
    assert contents.voxels().rows().tobytes() == arrays.rows().tobytes()
    assert (arrays.weighted_height_sum < 0).any() and (arrays.weighted_height_sum > 0).any()  # a signed sum, kept as it is
    again = save_map(tmp_path / "again.npz", load_map(path))
    assert again.read_bytes() == path.read_bytes()


def _parts(path):
    data = path.read_bytes()
    length = int.from_bytes(data[len(MAGIC):len(MAGIC) + 4], "little")
    start = len(MAGIC) + 4
    return json.loads(data[start:start + length]), data[start + length:]


def _rewrite_v3(path, out, header=None, payload=None, *, fix_checks=True):
    """``path`` with header keys replaced and/or another payload (its size and CRC made to match unless
    ``fix_checks`` is off)."""
    import struct
    import zlib

    head, body = _parts(path)
    head |= header or {}
    if payload is not None:
        body = payload
        if fix_checks:
            head |= {"payload_bytes": len(body), "payload_crc32": zlib.crc32(body)}
    text = json.dumps(head, sort_keys=True).encode()
    out.write_bytes(MAGIC + struct.pack("<I", len(text)) + text + body)
    return out


def _payload_of(local, rows, dtype=np.uint16):
    from evsemmap_warp.core.tile_codec import compress_columns

    return compress_columns(local, rows, dtype)


def _v3_columns(path):
    from evsemmap_warp.core.tile_codec import decompress_columns, index_dtype

    head, body = _parts(path)
    local, rows = decompress_columns(body, head["voxels"], head["columns"], index_dtype(max(head["index_extent"])), path)
    return head, local, rows


def _with_rows(change):
    def payload(head, local, rows):
        rows = rows.copy()
        change(rows)
        return _payload_of(local, rows, _dtype(head))
    return payload


def _with_local(change):
    def payload(head, local, rows):
        local = local.copy()
        change(local)
        return _payload_of(local, rows, _dtype(head))
    return payload


def _dtype(head):
    from evsemmap_warp.core.tile_codec import index_dtype

    return index_dtype(max(head["index_extent"]))


def _lying_frame(head, local, rows):
    """A zstd frame whose header declares 2**40 bytes (the CRC over it recomputed): a liar that checks out."""
    body = bytearray(_payload_of(local, rows, _dtype(head)))
    descriptor = body[4]  # frame header descriptor: the content-size field's width is its top two bits
    assert descriptor >> 6 in (1, 2, 3)
    width = {1: 2, 2: 4, 3: 8}[descriptor >> 6]
    at = 5 + (0 if descriptor & 0x20 else 1)  # window descriptor unless single-segment
    body[4] = (descriptor & 0x3F) | (3 << 6)  # widen the field to 8 bytes, then declare 2**40
    return bytes(body[:at]) + (2**40).to_bytes(8, "little") + bytes(body[at + width:])


def _consistent_lie(head, local, rows):
    """A header and a frame that agree on 10**9 voxels (CRC recomputed) over a payload of a few bytes."""
    count = 10**9
    expected = 3 * count * np.dtype(_dtype(head)).itemsize + (head["columns"] - 1) * count * 8 + (count + 7) // 8
    body = bytearray(_payload_of(local, rows, _dtype(head)))
    descriptor = body[4]
    width = {0: 1 if descriptor & 0x20 else 0, 1: 2, 2: 4, 3: 8}[descriptor >> 6]
    at = 5 + (0 if descriptor & 0x20 else 1)
    body[4] = (descriptor & 0x3F) | (3 << 6)
    return bytes(body[:at]) + expected.to_bytes(8, "little") + bytes(body[at + width:])


V3_CASES = {
    "consistent-lie": (_consistent_lie, "cannot hold the .* bytes of 1000000000 voxels", {"voxels": 10**9}),
    "truncated-payload": (lambda h, l, r: None, "truncated", {"payload_bytes": 10**9}),
    "flipped-byte": ("flip", "checksum mismatch", {}),
    "lying-voxel-count": (None, "declares .* bytes, 1000000000 voxels", {"voxels": 10**9}),
    "lying-frame-size": (_lying_frame, "declares .* bytes", {}),
    "header-beyond-file": ("header", "bytes left for a", {}),
    "nan-evidence": (_with_rows(lambda r: r.__setitem__((0, 0), np.nan)), "'evidence' holds 1 NaN/inf", {}),
    "negative-weight": (_with_rows(lambda r: r.__setitem__((0, 3), -1.0)), "'weight_sum' holds negative", {}),
    "fractional-hits": (_with_rows(lambda r: r.__setitem__((0, 5), 0.5)), "'hits' holds values that are not whole", {}),
    "duplicate-index": (_with_local(lambda a: a.__setitem__(1, a[0])), "appears more than once", {}),
    "out-of-order": (_with_local(lambda a: a.__setitem__(slice(0, 2), a[[1, 0]])), "out of key order", {}),
    "beyond-extent": (None, "beyond the header's index_extent", {"index_extent": [1, 1, 1]}),
    "index-out-of-range": (None, "outside the key range", {"index_low": [1 << 22, 0, 0]}),
    "resolution-disagrees": (None, "disagrees with meta.mapping.resolution_m", {"resolution": 0.5}),
    "origin-off-lattice": (None, "not on the voxel lattice", {"origin": [0.05, 0.0, 0.0]}),
    "wrong-columns": (None, "header says 12 columns, 3 classes need 8", {"columns": 12}),
    "nan-height": (_with_rows(lambda r: r.__setitem__((0, 6), np.inf)), "'weighted_height_sum' holds 1 NaN/inf", {}),
    # a map written before the weighted height sum (K + 4 columns) is refused, not read with centers for heights:
    # a first release has no users with such files, and a refusal never passes a coarser map off as this one
    "without-heights": (lambda h, l, r: _payload_of(l, np.delete(r, 6, axis=1), _dtype(h)),
                        "7 columns for 3 classes, without the weighted height sum .* map the data again", {"columns": 7}),
    "bad-header-key": (None, "header key 'voxels' = 'many'", {"voxels": "many"}),
}


@pytest.fixture
def tiny_map_file(tmp_path):
    rng = np.random.default_rng(0)
    mapper = Mapper(load_config([REPO / "configs/presets/offroad.yaml"], method="ebs").mapping, 3)
    mapper.integrate(rng.uniform(-2, 2, (300, 3)), rng.gamma(1, 3, (300, 3)) + 1, payload_type="alpha")
    return mapper.save(tmp_path / "small.npz")


@pytest.mark.parametrize("case", sorted(V3_CASES))
def test_a_damaged_or_lying_version_3_file_is_refused(tmp_path, tiny_map_file, case):
    make_payload, pattern, header = V3_CASES[case]
    head, local, rows = _v3_columns(tiny_map_file)
    bad = tmp_path / f"{case}.npz"
    if make_payload == "flip":
        data = bytearray(tiny_map_file.read_bytes())
        data[-20] ^= 0xFF
        bad.write_bytes(bytes(data))
    elif make_payload == "header":
        bad.write_bytes(tiny_map_file.read_bytes()[:len(MAGIC) + 40])
    else:
        payload = make_payload(head, local, rows) if callable(make_payload) else None
        _rewrite_v3(tiny_map_file, bad, header, payload)
        if case == "truncated-payload":
            bad.write_bytes(bad.read_bytes()[:-100])
    with pytest.raises(MapFileError, match=pattern) as err:
        load_map(bad)
    assert str(bad) in str(err.value) and "\n" not in str(err.value)


def test_saving_holds_a_column_at_a_time_not_copies_of_the_map(small_map):
    import tracemalloc

    from evsemmap_warp.core.map_file import encode_map
    from evsemmap_warp.core.tile_codec import compress_columns, decompress_columns, index_dtype

    contents = small_map.contents_of(small_map.voxels().arrays, read_out=False)
    sums = contents.voxels().rows().nbytes
    tracemalloc.start()
    data = encode_map(contents)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < sums / 2 + 2 * len(data), (peak, sums, len(data))  # the one-shot payload took three copies of the sums
    # the payload is compress_columns's (the store's tiles'), only compressed column by column
    head, start = json.loads(data[12:12 + int.from_bytes(data[8:12], "little")]), 12 + int.from_bytes(data[8:12], "little")
    dtype = index_dtype(max(head["index_extent"]))
    local, rows = decompress_columns(data[start:], head["voxels"], head["columns"], dtype, "x")
    same = compress_columns(contents.index - head["index_low"], contents.voxels().rows(), dtype)
    other_local, other_rows = decompress_columns(same, head["voxels"], head["columns"], dtype, "x")
    np.testing.assert_array_equal(local, other_local)
    assert rows.tobytes() == other_rows.tobytes()
