"""The store format: format-2 tiles and partials are compact and exact, the streaming reduction's fold
gives the bits a one-shot sum gives, a format-1 store is refused naming its format (and so is a new run
into one), and a full disk (a real one, where this test may mount a small tmpfs) loses nothing: the
rerun resumes to the store an uninterrupted run writes."""

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import stop_reading_partials_at
from evsemmap_warp.apps.batch import BatchOptions, run_batch
from evsemmap_warp.apps.cli import main
from evsemmap_warp.core import map_store
from evsemmap_warp.core.map_store import MapStore, fold
from evsemmap_warp.core.mapper import load_map
from evsemmap_warp.core.voxel_map import add_duplicate_voxels
from evsemmap_warp.voxel_keys import pack_voxel_keys
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

V1 = Path(__file__).parent / "data" / "store_v1"


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("format") / "drive"
    generate_sequence(load_preset("tiny"), folder, progress=False)
    return folder


def _batch(sources, out, **options) -> dict:
    options = {"progress": False, "executor": "inline", "method": "ebs", **options}
    return run_batch([str(s) for s in sources], BatchOptions(out=out, **options), log=lambda m: None)


def _cli_error(capsys, *argv) -> str:
    code = main([str(a) for a in argv])
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("Warp CUDA warning")]
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], (code, err)
    return err[0]


def _random_partials(rng, chunks: int, tile_voxels: int, columns: int):
    """Chunks' partials of one tile: overlapping voxel sets (collisions), values of very different scales
    (so that the order of float64 additions shows), one chunk of a single voxel on the tile's far face."""
    parts = []
    for c in range(chunks):
        count = 1 if c == 1 else int(rng.integers(2, 60))
        local = rng.integers(0, 6, size=(count, 3)) if c != 1 else np.full((1, 3), tile_voxels - 1)
        local = np.unique(local, axis=0)
        rows = rng.random((len(local), columns)) * 10.0 ** rng.integers(-8, 9, size=(len(local), 1))
        rows[:, -3] = rng.integers(0, 1000, len(local))  # hits: whole counts
        rows[:, -2] -= rows[:, -2] * 2 * (rng.random(len(local)) < 0.5)  # the weighted height sum: signed
        rows[:, -1] = rng.random(len(local)) < 0.5  # touched
        parts.append((local + np.array([-3, 7, 2**19 // tile_voxels]) * tile_voxels, rows))
    return parts


def test_folding_chunk_by_chunk_gives_the_bits_of_one_sum():
    rng = np.random.default_rng(3)
    for trial in range(30):
        parts = _random_partials(rng, int(rng.integers(1, 8)), 32, 9 + 5)
        running = None
        for index, rows in parts:
            running = fold(running, index, rows)
        index = np.concatenate([p[0] for p in parts])
        base = index.min(axis=0)
        once = add_duplicate_voxels(index - base, np.concatenate([p[1] for p in parts]))
        np.testing.assert_array_equal(running[0], once.index + base)
        assert running[1].tobytes() == once.rows().tobytes(), trial
    empty = (np.zeros((0, 3), np.int64), np.zeros((0, 14)))
    assert fold(running, *empty) is running  # an empty partial changes nothing
    assert fold(None, *empty)[0].shape == (0, 3)
    assert fold(empty, *running)[1].tobytes() == running[1].tobytes()


def test_a_store_is_compact_and_exports_the_map(drive, tmp_path):
    summary = _batch([drive], tmp_path / "store")
    tiles = sorted((tmp_path / "store" / "tiles").glob(f"*{map_store.TILE_SUFFIX}"))
    assert len(tiles) == summary["tiles"] > 1
    bytes_per_voxel = sum(p.stat().st_size for p in tiles) / summary["voxels"]
    assert bytes_per_voxel <= 48, bytes_per_voxel  # the target; the map-file schema took 230
    assert not list((tmp_path / "store" / "work").rglob("*.vox"))  # every partial folded and deleted
    store = MapStore(tmp_path / "store")
    assert store.format_version == 3 and store.voxel_count == summary["voxels"]


def test_a_map_file_costs_about_what_its_store_costs(drive, tmp_path, capsys):
    _batch([drive], tmp_path / "store")
    store = MapStore(tmp_path / "store")
    path = store.to_mapper().save(tmp_path / "map.npz")
    store_bytes = sum(p.stat().st_size for p in (tmp_path / "store").rglob("*") if p.is_file())
    assert path.stat().st_size <= 2 * store_bytes, (path.stat().st_size, store_bytes)  # the npz of every array took ~20x
    reports = []
    for target in (path, tmp_path / "store"):
        assert main(["info", str(target)]) == 0
        reports.append(json.loads(capsys.readouterr().out))
    assert reports[0]["bounds_m"] == reports[1]["bounds_m"] and reports[0]["voxels"] == reports[1]["voxels"]
    low, high = np.asarray(reports[0]["bounds_m"])
    assert np.all(high - low > 5) and np.all(low < high)


def test_a_format_1_store_and_a_version_2_map_file_are_refused_naming_their_version(capsys):
    """What this repository's earlier writers left (tests/data/store_v1) is refused in one line that names
    the file, its version and the version this release reads."""
    from evsemmap_warp.core.map_file import MapFileError
    from evsemmap_warp.core.map_store import StoreError

    index = V1 / "store" / "store.json"
    with pytest.raises(StoreError, match=r"store format version 1; this evsemmap_warp reads version 3 only") as err:
        MapStore(V1 / "store")
    assert str(index) in str(err.value)
    with pytest.raises(MapFileError, match=r"map format version 2; this evsemmap_warp reads version 3 only") as err:
        load_map(V1 / "map.npz")
    assert str(V1 / "map.npz") in str(err.value)
    for command in (["info", V1 / "store"], ["export", V1 / "store", "--out", "never.npz"], ["info", V1 / "map.npz"]):
        line = _cli_error(capsys, *command)
        assert str(command[1]) in line and "reads version" in line


def test_a_new_run_refuses_an_old_store_naming_its_format(drive, tmp_path, capsys):
    finished = shutil.copytree(V1 / "store", tmp_path / "finished")
    line = _cli_error(capsys, "batch", drive, "--method", "ebs", "--out", finished, "--quiet")
    assert str(finished) in line and "a store of format 1" in line and "give a new --out" in line
    running = tmp_path / "running"  # a run of the old version, killed before it wrote store.json
    (running / "work").mkdir(parents=True)
    (running / "work" / "plan.json").write_text(json.dumps({"inputs": [], "method": "ebs"}))
    line = _cli_error(capsys, "batch", drive, "--method", "ebs", "--out", running, "--quiet")
    assert str(running) in line and "a store of format 1" in line
    assert sorted(p.name for p in running.rglob("*")) == ["plan.json", "work"]  # nothing written
    before_heights = tmp_path / "before_heights"  # a killed run of format 2, whose rows had no height sum
    (before_heights / "work").mkdir(parents=True)
    (before_heights / "work" / "plan.json").write_text(json.dumps({"inputs": [], "method": "ebs", "store_format_version": 2}))
    line = _cli_error(capsys, "batch", drive, "--method", "ebs", "--out", before_heights, "--quiet")
    assert str(before_heights) in line and "a store of format 2" in line and "reads format 3" in line


def _mount_small_tmpfs(folder: Path, size: str) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    folder.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True).returncode == 0


@pytest.mark.parametrize("size, writing", [("200k", "writing chunk 0's partial maps"), ("1350k", "writing tile")])
def test_a_full_disk_loses_nothing_and_the_rerun_resumes(drive, tmp_path, capsys, size, writing):
    """On a real full filesystem: a small tmpfs that fills up while the run writes (a partial map, or a
    tile being folded), grown once the error is shown, as a user would free space."""
    reference = tmp_path / "reference"
    _batch([drive], reference, chunk_frames=2)
    small = tmp_path / "small"
    if not _mount_small_tmpfs(small, size):
        pytest.skip("mounting a small tmpfs needs root and mount(8); the ENOSPC paths are tested with injected errors too")
    try:
        out = small / "store"
        argv = ["batch", drive, "--method", "ebs", "--out", out, "--chunk-frames", "2", "--workers", "1", "--quiet"]
        line = _cli_error(capsys, *argv)
        assert "No space left on device" in line and writing in line and str(out) in line and "rerun" in line, line
        assert not (out / "store.json").exists()
        subprocess.run(["mount", "-o", "remount,size=64m", str(small)], check=True)
        assert main([str(a) for a in argv]) == 0
        capsys.readouterr()
        for name in sorted(p.name for p in (reference / "tiles").iterdir()):
            assert (out / "tiles" / name).read_bytes() == (reference / "tiles" / name).read_bytes(), name
        assert (out / "store.json").read_bytes() == (reference / "store.json").read_bytes()
    finally:
        subprocess.run(["umount", "-l", str(small)], capture_output=True)


def test_tiles_leaving_memory_early_and_a_run_killed_while_folding_give_the_same_store(drive, tmp_path, monkeypatch):
    """With room for one tile in memory, tiles are written and read back at every turn of the drive;
    a run stopped halfway through folding (here: at the first partial of chunk 3) resumes from the tiles
    and partials it left, and both give the store, byte for byte, of an uninterrupted run."""
    from evsemmap_warp.apps.batch import reduction
    from evsemmap_warp.core import map_store

    reference = tmp_path / "reference"
    _batch([drive], reference, chunk_frames=1)
    monkeypatch.setattr(reduction, "FOLD_CACHE_TILES", 1)
    summary = _batch([drive], tmp_path / "evicting", chunk_frames=1)
    assert summary["tile_writes"] > summary["tiles"]  # tiles were written before the end and folded into again

    original = stop_reading_partials_at(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        _batch([drive], tmp_path / "killed", chunk_frames=1)
    assert list((tmp_path / "killed" / "tiles").glob("*.vox")) and not (tmp_path / "killed" / "store.json").exists()
    monkeypatch.setattr(map_store, "read_partial", original)
    resumed = _batch([drive], tmp_path / "killed", chunk_frames=1)
    assert resumed["chunks_resumed"] == 4
    for store in ("evicting", "killed"):
        for name in sorted(p.name for p in (reference / "tiles").iterdir()):
            assert (tmp_path / store / "tiles" / name).read_bytes() == (reference / "tiles" / name).read_bytes(), (store, name)
        assert (tmp_path / store / "store.json").read_bytes() == (reference / "store.json").read_bytes()
        assert not list((tmp_path / store / "work").rglob("*.vox"))


def test_duplicate_voxels_add_left_to_right_from_zero():
    # add_duplicate_voxels (a map's shards merged, a store's partials) keeps np.add.at's bits: each voxel's
    # rows added into zeros in input order, for runs of up to five rows and a -0.0 alone or repeated.
    rng = np.random.default_rng(11)
    index = rng.integers(-40, 40, (3000, 3))
    index[2000:] = index[rng.integers(0, 2000, 1000)]  # repeats, some of them several times
    rows = rng.random((3000, 14)) * 10.0 ** rng.uniform(-8, 8, (3000, 14))
    rows[:, -3] = rng.integers(0, 50, 3000)  # hits, a count
    rows[:, -2] -= 0.5  # the weighted height sum, signed
    rows[:, -1] = rng.random(3000) < 0.5  # touched
    rows[rng.integers(0, 3000, 200), rng.integers(0, 11, 200)] = -0.0
    keys, first, inverse = np.unique(pack_voxel_keys(index), return_index=True, return_inverse=True)
    want = np.zeros((len(keys), 14))
    np.add.at(want, inverse.reshape(-1), rows)
    want[:, -1] = np.minimum(want[:, -1], 1.0)
    got = add_duplicate_voxels(index, rows)
    assert np.bincount(inverse.reshape(-1)).max() >= 4
    np.testing.assert_array_equal(got.index, index[first])
    assert got.rows().tobytes() == want.tobytes()
    assert add_duplicate_voxels(index[:0], rows[:0]).rows().shape == (0, 14)
