"""Stores and runs you can trust (issue 31): a batch run is identified by the content of what it reads,
a merge never counts a scan twice, a tile that does not belong to its store is refused naming it,
store.json and the work files are validated, nothing is written inside an input, a store answers a
query outside its tiles as the same map as a file does, its tiles cannot be changed behind its back,
and a refused scan changes nothing. Each test failed before its fix."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from evsemmap_warp.apps.batch import BatchOptions, run_batch
from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.core import tile_codec
from evsemmap_warp.core.map_store import MapStore, StoreError
from evsemmap_warp.core.mapper import Mapper, load_map
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("trust") / "drive"
    generate_sequence(load_preset("tiny"), folder, progress=False)
    return folder


@pytest.fixture(scope="module")
def store(drive, tmp_path_factory):
    out = tmp_path_factory.mktemp("stores") / "ebs"
    _batch([drive], out)
    return out


def _batch(sources, out, method="ebs", **options) -> dict:
    options = {"progress": False, "executor": "inline", **options}
    return run_batch([str(s) for s in sources], BatchOptions(method=method, out=out, **options), log=lambda m: None)


def _cli_error(capsys, *argv) -> str:
    """Run the CLI; exit 2, one line, no traceback; the line."""
    code = main([str(a) for a in argv])
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("Warp CUDA warning")]
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], (code, err)
    return err[0]


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# Identity by content --------------------------------------------------------------------------------
def test_an_edited_scan_of_the_same_size_and_mtime_is_a_different_run(drive, tmp_path):
    """A run used to be identified by the folder's mtime: an edited scan resumed the old run and the
    store kept the old data. Even an edit that keeps the file's size and mtime (cp -p) is seen now."""
    seq = _copy(drive, tmp_path / "seq")
    out = tmp_path / "store"
    _batch([seq], out)
    scan = sorted((seq / "os1_cloud_node_kitti_bin").glob("*.bin"))[2]
    stat = scan.stat()
    points = np.fromfile(scan, np.float32)
    points[0::4] += 3.0
    points.tofile(scan)
    os.utime(scan, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert scan.stat().st_size == stat.st_size and scan.stat().st_mtime_ns == stat.st_mtime_ns
    with pytest.raises(ConfigError, match="holds a batch run of other inputs or settings .differing: inputs"):
        _batch([seq], out)
    # a new store of the edited drive is the map `map` makes of it
    _batch([seq], tmp_path / "edited")
    run = load_config([str(seq)], method="ebs")
    from evsemmap_warp.data.datasets import open_dataset

    dataset = open_dataset(run.dataset)
    mapper = Mapper(run.mapping, dataset.num_classes, class_names=dataset.class_names)
    mapper.integrate_many(dataset)
    assert MapStore(tmp_path / "edited").voxel_count == mapper.voxel_count


def test_the_same_drive_twice_in_one_batch_is_refused(drive, tmp_path):
    copy = _copy(drive, tmp_path / "copy")
    with pytest.raises(ConfigError, match="hold the same data"):
        _batch([drive, copy], tmp_path / "store")
    assert not (tmp_path / "store").exists()


# Inputs counted twice -------------------------------------------------------------------------------
def test_merge_refuses_a_scan_held_twice(drive, store, tmp_path, capsys):
    assert main(["map", str(drive), "--method", "ebs", "--out", str(tmp_path / "m.npz"), "--quiet"]) == 0
    assert main(["export", str(store), "--out", str(tmp_path / "export.npz")]) == 0
    assert main(["export", str(store), "--bounds", "-inf", "-inf", "-inf", "0", "inf", "inf", "--out", str(tmp_path / "half.npz")]) == 0
    capsys.readouterr()
    for a, b in ((store, store), (tmp_path / "m.npz", tmp_path / "m.npz"), (store, tmp_path / "export.npz"),
                 (tmp_path / "m.npz", store), (tmp_path / "half.npz", store)):
        line = _cli_error(capsys, "merge", a, b, "--out", tmp_path / "merged.npz")
        assert "given twice" in line or "scan(s) in common" in line, line
    assert not (tmp_path / "merged.npz").exists()
    # the API says the same; maps of disjoint scans still merge
    with pytest.raises(ValueError, match="6 scan.s. in common"):
        load_map(tmp_path / "m.npz").merge(load_map(tmp_path / "m.npz"))
    with pytest.raises(ValueError, match="must be a Mapper, got NoneType"):
        load_map(tmp_path / "m.npz").merge(None)


def test_map_refuses_a_log_given_twice(drive, tmp_path, capsys):
    pytest.importorskip("rosbags")
    from evsemmap_warp.data.log_writer import write_log

    log = tmp_path / "t.bag"
    write_log(drive, log, "rosbag1", frames=slice(0, 2))
    shutil.copy(log, tmp_path / "copy.bag")
    assert "is given twice" in _cli_error(capsys, "map", log, log, "--method", "ebs", "--out", tmp_path / "m.npz")
    assert "repeat a stamp" in _cli_error(capsys, "map", log, tmp_path / "copy.bag", "--method", "ebs", "--out", tmp_path / "m.npz")


# Integrity ------------------------------------------------------------------------------------------
def test_a_tile_that_does_not_belong_is_refused_naming_it(drive, store, tmp_path, capsys):
    other = tmp_path / "scsm"
    _batch([drive], other, method="s-csm")
    coarse = tmp_path / "coarse"
    _batch([drive], coarse, tile_voxels=128)
    (tmp_path / "fine.yaml").write_text("mapping:\n  resolution_m: 0.25\n")
    fine = tmp_path / "fine"
    _batch([drive, tmp_path / "fine.yaml"], fine)
    names = sorted(p.name for p in (store / "tiles").iterdir())
    cases = {
        "another method": (other / "tiles" / names[0], names[0], "method 's-csm' vs 'ebs'"),
        "another place": (store / "tiles" / names[1], names[0], f"it is tile {names[1][:-4]}, not {names[0][:-4]}"),
        "another tiling": (sorted((coarse / "tiles").iterdir())[0], names[0], "written for another store"),
        "another resolution": (sorted((fine / "tiles").iterdir())[0], names[0], "its resolution_m 0.25 vs 0.2"),
    }
    for case, (source, name, pattern) in cases.items():
        copy = _copy(store, tmp_path / case.replace(" ", "_"))
        shutil.copy(source, copy / "tiles" / name)
        line = _cli_error(capsys, "export", copy, "--out", tmp_path / "out.npz")
        assert str(copy / "tiles" / name) in line and pattern in line and "does not belong" in line, (case, line)
    # a tile damaged after writing: its checksum; a partial map or an old-format tile in its place
    copy = _copy(store, tmp_path / "damaged")
    tile = copy / "tiles" / names[0]
    data = bytearray(tile.read_bytes())
    data[-9] ^= 0xFF
    tile.write_bytes(bytes(data))
    assert "payload checksum mismatch" in _cli_error(capsys, "export", copy, "--out", tmp_path / "out.npz")
    assert not (tmp_path / "out.npz").exists()
    copy = _copy(store, tmp_path / "a-map-file")
    tile = copy / "tiles" / names[0]
    MapStore(store).to_mapper().save(tmp_path / "whole.npz")
    shutil.copy(tmp_path / "whole.npz", tile)
    line = _cli_error(capsys, "export", copy, "--out", tmp_path / "out.npz")
    assert str(tile) in line and "not a store voxel file" in line, line
    # a tile of K + 4 columns, as stores were written before the weighted height sum: refused, not read with centers
    copy = _copy(store, tmp_path / "without-heights")
    tile = copy / "tiles" / names[0]
    header, index, rows = tile_codec.read_voxel_file(tile)
    identity = {key: header[key] for key in ("kind", "store", "mapping", "classes", "frame", "entry", "folded_through")}
    tile_codec.write_voxel_file(tile, index, np.delete(rows, -2, axis=1), header["tile"], header["tile_voxels"], identity)
    line = _cli_error(capsys, "export", copy, "--out", tmp_path / "out.npz")
    assert str(tile) in line and "the weighted height sum is missing" in line and "map the data again" in line, line


def test_a_tile_file_the_index_does_not_list_is_refused_naming_it(store, tmp_path, capsys):
    """store.json without one tile whose file is still there: every read-out (export, merge, layers, view,
    info) lacked its voxels and exited 0; a listed tile missing on disk was already refused, naming it."""
    copy = _copy(store, tmp_path / "store")
    index = json.loads((copy / "store.json").read_text())
    name = sorted(index["tiles"])[0]
    del index["tiles"][name]
    (copy / "store.json").write_text(json.dumps(index))
    tile = copy / "tiles" / f"{name}.vox"
    for argv in (["export", copy, "--out", tmp_path / "out.npz"], ["merge", copy, store, "--out", tmp_path / "out.npz"],
                 ["layers", copy, "--out", tmp_path / "layers"], ["view", copy, "--no-serve", "--port", "18411"], ["info", copy]):
        line = _cli_error(capsys, *argv)
        assert line.startswith(f"evsemmap: error: {tile}: a tile file that {copy / 'store.json'} does not list"), (argv[0], line)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["store"]


def test_a_store_a_batch_run_is_still_writing_is_named_so_by_every_reader(drive, tmp_path, capsys):
    """A folder batch has begun (work/, tiles/, no store.json yet), or a copy taken of one: view, layers
    and merge said "cannot read the map file (Is a directory)"; every reader now says what it is."""
    unfinished = tmp_path / "unfinished"
    (unfinished / "work").mkdir(parents=True)
    (unfinished / "tiles").mkdir()
    other = _copy(unfinished, tmp_path / "other")
    for argv in (["export", unfinished, "--out", tmp_path / "out.npz"], ["merge", unfinished, other, "--out", tmp_path / "out.npz"],
                 ["layers", unfinished, "--out", tmp_path / "layers"], ["view", unfinished, "--no-serve", "--port", "18412"],
                 ["info", unfinished]):
        line = _cli_error(capsys, *argv)
        assert f"{unfinished}: not a map store, no store.json (a batch run still writing it" in line, (argv[0], line)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other", "unfinished"]


STORE_INDEX_CASES = {
    "origin-2^70": (lambda i: i.update(origin_index=[2**70, 0, 0]), "origin_index must be 3 whole numbers"),
    "origin-short": (lambda i: i.update(origin_index=[0, 0]), "origin_index must be 3 whole numbers"),
    "origin-text": (lambda i: i.update(origin_index=["0", 0, 0]), "origin_index must be 3 whole numbers"),
    "states-list": (lambda i: [t.update(states=[1, 2, 3]) for t in i["tiles"].values()], "states must map"),
    "states-off": (lambda i: [t["states"].update(FREE=t["states"]["FREE"] + 1) for t in i["tiles"].values()], "adding up to"),
    "classes-cut": (lambda i: i.update(classes=i["classes"][:-1]), "were changed after it was written"),
    "parameters-edited": (lambda i: i["mapping"].update(length_m=0.5), "were changed after it was written"),
    "negative-voxels": (lambda i: [t.update(voxels=-5) for t in i["tiles"].values()], "voxel count >= 1"),
    "negative-scans": (lambda i: i.update(scans=-3), "scans = -3 is negative"),
    "negative-points": (lambda i: i.update(points=-3), "points = -3 is negative"),
    "scans-do-not-add-up": (lambda i: i.update(scans=99), "the chunks hold 6 scans"),
    "tile-voxels-bool": (lambda i: i.update(tile_voxels=True), "tile_voxels"),
    "bounds-text": (lambda i: [t.update(bounds_m=[[0, 0, "x"], [1, 1, 1]]) for t in i["tiles"].values()], "bounds_m must be"),
    "scan-ids-not-a-list": (lambda i: i.update(scan_ids="abc"), "scan_ids must be a list"),
}


@pytest.mark.parametrize("case", sorted(STORE_INDEX_CASES))
def test_a_store_index_that_does_not_add_up_is_one_line(store, tmp_path, capsys, case):
    change, pattern = STORE_INDEX_CASES[case]
    copy = _copy(store, tmp_path / "store")
    index = json.loads((copy / "store.json").read_text())
    change(index)
    (copy / "store.json").write_text(json.dumps(index))
    for argv in (["info", copy], ["export", copy, "--out", tmp_path / "out.npz"], ["merge", copy, tmp_path / "none.npz", "--out", tmp_path / "m.npz"]):
        line = _cli_error(capsys, *argv)
        assert str(copy / "store.json") in line and pattern in line, line
    with pytest.raises(StoreError, match=pattern):
        MapStore(copy)


def _first_chunk(store: Path) -> Path:
    return sorted((store / "work").glob("chunk_*"))[0]


@pytest.fixture(scope="module")
def unfolded(drive, tmp_path_factory):
    """A run killed after mapping every chunk and before folding any: partials of every chunk, no tile."""
    from evsemmap_warp.apps import batch

    out = tmp_path_factory.mktemp("unfolded") / "store"
    original = batch.TileFolder.chunk_finished
    batch.TileFolder.chunk_finished = lambda self, number: self.finished.add(number)
    try:
        with pytest.raises(RuntimeError, match="was mapped but not folded"):
            _batch([drive], out)
    finally:
        batch.TileFolder.chunk_finished = original
    assert not list((out / "tiles").glob("*.vox")) and len(list(_first_chunk(out).glob("*.vox"))) >= 1
    return out


def _partial(s: Path, number: int = 0) -> Path:
    return sorted(sorted((s / "work").glob("chunk_*"))[number].glob("*.vox"))[0]


WORK_CASES = {
    "plan-garbage": (lambda s: (s / "work" / "plan.json").write_text("{oops"), "plan.json: not a readable batch plan"),
    "plan-a-list": (lambda s: (s / "work" / "plan.json").write_text("[1]"), "plan.json: not a batch plan"),
    "done-garbage": (lambda s: (_first_chunk(s) / "done.json").write_text("nope"), "done.json: not a readable chunk record"),
    "done-negative": (lambda s: (_first_chunk(s) / "done.json").write_text(
        json.dumps(json.loads((_first_chunk(s) / "done.json").read_text()) | {"scans": -1})), "whole counts >= 0"),
    "done-another-chunk": (lambda s: (_first_chunk(s) / "done.json").write_text(
        json.dumps(json.loads((_first_chunk(s) / "done.json").read_text()) | {"number": 7})), "says chunk 7"),
    "partial-truncated": (lambda s: (lambda p: p.write_bytes(p.read_bytes()[:300]))(_partial(s)), "the header says"),
    "partial-missing": (lambda s: _partial(s).unlink(), "whose partial"),
    "partial-of-the-old-format": (lambda s: (lambda p: p.write_bytes(b"PK\x03\x04" + p.read_bytes()))(_partial(s)),
                                  "not a store voxel file"),
    "partial-of-another-chunk": (lambda s: shutil.copy(sorted((s / "work").glob("chunk_*"))[1] / _partial(s).name, _partial(s)),
                                 "chunk is 1, this store's is 0"),
}


@pytest.mark.parametrize("case", sorted(WORK_CASES))
def test_damaged_work_files_are_one_line_naming_them(drive, unfolded, tmp_path, capsys, case):
    damage, pattern = WORK_CASES[case]
    copy = _copy(unfolded, tmp_path / "store")
    damage(copy)
    line = _cli_error(capsys, "batch", drive, "--method", "ebs", "--out", copy, "--workers", "1", "--quiet")
    assert pattern in line and str(copy / "work") in line, line


def test_no_write_goes_inside_an_input(drive, store, tmp_path, capsys):
    before = (store / "store.json").read_bytes()
    assert "lies inside the input" in _cli_error(capsys, "export", store, "--out", store / "store.json")
    assert (store / "store.json").read_bytes() == before and MapStore(store).voxel_count > 0
    assert "lies inside the input" in _cli_error(capsys, "merge", store, tmp_path / "x.npz", "--out", store / "tiles" / "m.npz")
    seq = _copy(drive, tmp_path / "seq")
    assert "lies inside the input" in _cli_error(capsys, "map", seq, "--method", "ebs", "--out", seq / "map.npz")
    assert "lies inside the input" in _cli_error(capsys, "batch", seq, "--method", "ebs", "--out", seq / "store", "--quiet")
    assert not (seq / "map.npz").exists() and not (seq / "store").exists()
    # map --out over a config file, the method file or the checkpoint; map / batch --out inside the alpha files
    preset = Path(shutil.copy(REPO / "configs/presets/offroad.yaml", tmp_path / "offroad.yaml"))
    method = Path(shutil.copy(REPO / "configs/methods/ebs.yaml", tmp_path / "ebs.yaml"))
    checkpoint, alpha = tmp_path / "seg.pt", tmp_path / "alpha"
    checkpoint.write_bytes(b"a checkpoint")
    alpha.mkdir()
    kept = {path: path.read_bytes() for path in (preset, method, checkpoint)}
    for argv in (["map", seq, preset, "--method", "ebs", "--out", preset],
                 ["map", seq, "--method", method, "--out", method],
                 ["map", seq, "--method", "ebs", "--checkpoint", checkpoint, "--out", checkpoint],
                 ["map", seq, "--method", "ebs", "--alpha-dir", alpha, "--out", alpha / "map.npz"],
                 ["batch", seq, "--method", "ebs", "--alpha-dir", alpha, "--out", alpha / "store", "--quiet"]):
        line = _cli_error(capsys, *argv)
        assert ("is the input" in line or "lies inside the input" in line) and str(argv[argv.index("--out") + 1]) in line, (argv, line)
    assert {path: path.read_bytes() for path in kept} == kept and not list(alpha.iterdir())
    # view --export-ply / --export-html over a map given or inside a store
    from evsemmap_warp.apps.viewer import free_port

    assert main(["export", str(store), "--out", str(tmp_path / "m.npz")]) == 0
    capsys.readouterr()
    kept = (tmp_path / "m.npz").read_bytes()
    for flag, maps, out in (("--export-ply", [tmp_path / "m.npz"], tmp_path / "m.npz"), ("--export-html", [tmp_path / "m.npz"], tmp_path / "m.npz"),
                            ("--export-ply", [store], store / "store.json"), ("--export-html", [tmp_path / "m.npz", store], store / "view.html")):
        line = _cli_error(capsys, "view", *maps, flag, out, "--no-serve", "--port", free_port())
        assert f"view {flag} {out}" in line and ("is the input" in line or "lies inside the input" in line), line
    assert (tmp_path / "m.npz").read_bytes() == kept and (store / "store.json").read_bytes() == before
    assert not (store / "view.html").exists()


# One semantics --------------------------------------------------------------------------------------
def test_a_store_answers_as_its_map_file_outside_its_tiles_and_its_tiles_are_read_only(store, tmp_path):
    opened = MapStore(store)
    as_file = opened.to_mapper()
    as_file.save(tmp_path / "m.npz")
    as_file = load_map(tmp_path / "m.npz")
    far = np.array([[5000.0, 5000.0, 0.0], [0.0, 0.0, 3000.0]])
    inside = as_file.voxel_centers(as_file.voxels()[0].index[:20])
    points = np.concatenate([far, inside])
    a, b = opened.query(points), as_file.query(points)
    np.testing.assert_array_equal(a.label, b.label)
    np.testing.assert_array_equal(a.state, b.state)
    np.testing.assert_allclose(a.probabilities, b.probabilities)
    np.testing.assert_allclose(a.variance, b.variance)
    assert np.allclose(a.probabilities[:2], 1 / opened.num_classes)  # the prior, not zeros
    name = sorted(opened.tiles)[0]
    tile = opened.tile(name)
    before = opened.query(inside).probabilities
    with pytest.raises(ValueError, match=f"read-only: tile {name} of the store"):
        tile.integrate(inside, np.ones(len(inside), np.int64), payload_type="label")
    np.testing.assert_array_equal(opened.query(inside).probabilities, before)


@pytest.mark.parametrize("method", ["ebs", "s-csm"])
def test_a_refused_scan_changes_nothing_with_two_workers(method):
    """The shards used to check only their own part of a scan: with two workers the near half of a
    scan reaching outside the key range was written, and the scan counted, before the refusal."""
    config = load_config([REPO / "configs/presets/offroad.yaml"], method=method).mapping
    rng = np.random.default_rng(0)
    near = rng.normal(size=(20000, 3))
    labels = np.ones(len(near), np.int64)
    mapper = Mapper(config, 9, workers=2)
    mapper.integrate(near, labels, payload_type="label")
    before = (mapper.scans_integrated, mapper.points_integrated, mapper.voxel_count, mapper.voxels()[0].hits.sum(), set(mapper.scan_ids))
    reaching = near + [5.0, 0, 0]
    reaching[15000:] += [1e6, 0, 0]  # the second shard's part lies 1,000 km away
    with pytest.raises(ValueError, match="outside the key range"):
        mapper.integrate(reaching, labels, payload_type="label")
    assert (mapper.scans_integrated, mapper.points_integrated, mapper.voxel_count, mapper.voxels()[0].hits.sum(), mapper.scan_ids) == before
    fresh = Mapper(config, 9, workers=2)  # a refused first scan leaves no origin behind
    with pytest.raises(ValueError, match="outside the key range"):
        fresh.integrate(reaching, labels, payload_type="label")
    assert fresh.origin_index is None and fresh.scans_integrated == 0


# Bounds and API arguments -----------------------------------------------------------------------------
def test_bounds_that_mean_nothing_are_refused_and_minus_inf_is_a_value(store, tmp_path, capsys):
    for bounds, pattern in ((["nan", "0", "0", "1", "1", "1"], "NaN is no coordinate"), (["1", "0", "0", "0", "1", "1"], "each minimum")):
        line = _cli_error(capsys, "export", store, "--bounds", *bounds, "--out", tmp_path / "out.npz")
        assert "--bounds" in line and pattern in line
    assert not (tmp_path / "out.npz").exists()
    assert main(["export", str(store), "--bounds", "-inf", "-inf", "-inf", "inf", "inf", "inf", "--out", str(tmp_path / "all.npz")]) == 0
    assert json.loads(capsys.readouterr().out)["voxels"] == MapStore(store).voxel_count
    opened = MapStore(store)
    for bounds, pattern in (([[np.nan, 0, 0], [1, 1, 1]], "NaN"), ([[1, 0, 0], [0, 1, 1]], "each minimum"), ([0, 0, 0, 1], "6 numbers")):
        with pytest.raises(ValueError, match=pattern):
            opened.to_mapper(np.asarray(bounds))
    for value in (-1, 2.5, "3", True):
        with pytest.raises(ValueError, match="cache_tiles"):
            MapStore(store, cache_tiles=value)


def test_a_second_batch_run_into_a_store_being_written_is_refused(drive, tmp_path):
    """Two runs into one store interleaved their plans, chunks and tiles: a store listing one drive
    held the other's voxels, both runs exiting 0."""
    from evsemmap_warp.apps.batch import store_lock

    out = tmp_path / "store"
    with store_lock(out):  # a run in progress
        with pytest.raises(ConfigError, match="another batch run is writing this store now"):
            _batch([drive], out)
    _batch([drive], out)  # once it is done, the store is free
    assert MapStore(out).voxel_count > 0
    with store_lock(tmp_path / "unused"):
        pass
    assert not (tmp_path / "unused").exists()  # a refused or failed run leaves no empty folder behind


def test_a_full_disk_while_mapping_a_chunk_names_the_store_and_leaves_nothing_half_written(drive, tmp_path, monkeypatch):
    """The error named the chunk's temporary folder; now it names the store, removes the temporary
    folder, and a rerun once there is room resumes to the store an uninterrupted run writes."""
    import errno

    from evsemmap_warp.core import map_store

    original = map_store.write_partial

    def full(path, *args):  # the disk fills up while the third chunk is written
        if ".chunk_000002." in str(path):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return original(path, *args)

    out = tmp_path / "store"
    monkeypatch.setattr(map_store, "write_partial", full)
    with pytest.raises(OSError, match=r"No space left on device \(writing chunk \d+'s partial maps.*rerun to resume\)") as refused:
        _batch([drive], out)
    assert refused.value.filename == str(out)
    assert not list((out / "work").glob(".chunk_*")) and not (out / "store.json").exists()
    monkeypatch.setattr(map_store, "write_partial", original)
    (out / "tiles").mkdir(exist_ok=True)
    (out / "tiles" / ".0_0_0.vox.123.abcd.tmp").write_bytes(b"half a tile")  # what a killed writer leaves
    summary = _batch([drive], out)
    assert summary["chunks_resumed"] >= 1 and not list((out / "tiles").glob(".*.tmp"))
    _batch([drive], tmp_path / "reference")
    for name in sorted(p.name for p in (tmp_path / "reference" / "tiles").iterdir()):
        assert (out / "tiles" / name).read_bytes() == (tmp_path / "reference" / "tiles" / name).read_bytes()
