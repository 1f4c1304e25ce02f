"""Maps anchored in the world (docs/algorithm.md §6.1): a map is made in the frame its data lives in
(a log's fixed frame, a folder's poses frame, point files' own frame) and records it; maps merge only
within one frame, and halves of a drive merged equal the whole; the paper's first-scan convention
stays available; georeferenced poses keep their coordinates; one voxel-index routine answers for
maps and stores alike, far from the origin too."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from evsemmap_warp.apps.batch import BatchOptions, run_batch
from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.core.map_store import MapStore
from evsemmap_warp.core.mapper import Mapper, load_map
from evsemmap_warp.data.datasets import open_dataset
from evsemmap_warp.data.sequences import DataError, Rellis3DSequence, read_frame_file, read_poses
from evsemmap_warp.frames import FrameError, WorldFrame, check_crs
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence
from evsemmap_warp.voxel_keys import voxel_index_of


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    root = tmp_path_factory.mktemp("frames")
    folder = root / "folder"
    generate_sequence(load_preset("tiny"), folder, progress=False)
    return folder


def _map(sources, method="s-csm", **frame):
    run = load_config([str(s) for s in sources], method=method, **frame)
    dataset = open_dataset(run.dataset)
    mapper = Mapper.for_dataset(dataset, run.mapping)
    mapper.integrate_many(dataset)
    return mapper


def _assert_same_map(a: Mapper, b: Mapper, evidence_tol=1e-9):
    (va, sa), (vb, sb) = a.voxels(), b.voxels()
    np.testing.assert_array_equal(va.index, vb.index)
    np.testing.assert_array_equal(sa.label, sb.label)
    np.testing.assert_array_equal(va.hits, vb.hits)
    np.testing.assert_allclose(va.evidence, vb.evidence, rtol=evidence_tol, atol=evidence_tol)
    # heights above the voxels' centers: the same whatever the origin each map had
    np.testing.assert_allclose(va.weighted_height_sum, vb.weighted_height_sum, rtol=evidence_tol, atol=evidence_tol)


def _copy_folder(folder: Path, out: Path, frames=None, transform=None, frame_file: str | None = "keep") -> Path:
    """A copy of a sequence folder: some of its scans (all by default), the poses moved by
    ``transform`` (applied on the left), and its frame.yaml kept, replaced or dropped."""
    shutil.copytree(folder, out)
    if frames is not None:
        keep = {f"{i:06d}" for i in frames}
        for path in out.rglob("*"):
            stem = path.stem.removeprefix("frame")[:6]
            if path.is_file() and path.parent != out and stem.isdigit() and stem not in keep:
                path.unlink()
    if transform is not None:
        poses = transform @ read_poses(out / "poses.txt")
        np.savetxt(out / "poses.txt", poses[:, :3, :].reshape(len(poses), 12), fmt="%.17g")
    if frame_file != "keep":
        (out / "frame.yaml").unlink()
        if frame_file is not None:
            (out / "frame.yaml").write_text(frame_file)
    return out


def test_a_folder_is_mapped_in_its_poses_frame_as_given(drive):
    mapper = _map([drive])
    # evsemmap synth names its poses' frame in frame.yaml, and odom's run: the preset's drive
    assert mapper.frame == WorldFrame("odom", run=read_frame_file(drive).run) and mapper.frame.run
    seq = Rellis3DSequence(drive)
    assert not np.allclose(seq.pose(seq.frames[0]), np.eye(4))  # the synthetic poses are world poses
    # The first scan's points land where its world pose puts them, not at its LiDAR frame.
    scan = next(iter(open_dataset(load_config([str(drive)], method="s-csm").dataset)))
    first = seq.read_scan(seq.frames[0])
    first = first[np.any(first[:, :3] != 0, axis=1), :3].astype(np.float64)
    np.testing.assert_allclose(scan.points, first @ seq.pose(seq.frames[0])[:3, :3].T + seq.pose(seq.frames[0])[:3, 3], atol=1e-9)
    np.testing.assert_allclose(scan.sensor_origin, seq.pose(seq.frames[0])[:3, 3])


def test_first_scan_keeps_the_papers_convention_and_identity_poses_map_as_before(drive, tmp_path):
    seq = Rellis3DSequence(drive)
    first = seq.pose(seq.frames[0])
    relative = _map([drive], frame="first-scan")
    assert relative.frame.name == f"first-scan of {drive.name}" and relative.frame.crs is None
    # A KITTI-style folder (first pose the identity): its own frame is the first scan's.
    kitti = _copy_folder(drive, tmp_path / "kitti", transform=np.linalg.inv(first), frame_file=None)
    own = _map([kitti])
    assert own.frame.name == "poses:kitti"
    _assert_same_map(relative, own, evidence_tol=1e-6)
    # and the default is the world frame: the same scans on the world's lattice, other voxels
    world = _map([drive])
    assert world.frame == read_frame_file(drive) and len(world.voxels()[0].index) != len(relative.voxels()[0].index)


def test_halves_of_a_drive_in_two_folders_of_one_frame_merge_into_the_whole(drive, tmp_path, capsys):
    whole = _map([drive])
    first = _copy_folder(drive, tmp_path / "a", frames=range(0, 3))
    second = _copy_folder(drive, tmp_path / "b", frames=range(3, 6))
    halves = _map([first]).merge(_map([second]))
    _assert_same_map(whole, halves)
    # on the command line, as map files and as a multi-input batch store
    for half, name in ((first, "a.npz"), (second, "b.npz")):
        assert main(["map", str(half), "--method", "s-csm", "--out", str(tmp_path / name), "--quiet"]) == 0
    assert main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "ab.npz")]) == 0
    _assert_same_map(whole, load_map(tmp_path / "ab.npz"))
    run_batch([str(first), str(second)], BatchOptions(method="s-csm", out=tmp_path / "store", executor="inline", progress=False),
              log=lambda message: None)
    store = MapStore(tmp_path / "store")
    assert store.frame == read_frame_file(drive)
    _assert_same_map(whole, store.to_mapper())
    capsys.readouterr()


def test_a_map_made_in_python_as_the_readme_shows_merges_with_the_command_lines(drive, tmp_path, monkeypatch, capsys):
    """The README's Python block, run as written on the first half of a drive, makes its map in the folder's
    world frame as `evsemmap map` does (Mapper.for_dataset, the one place both build their mapper): `info`
    names the frame, and the map merges with the command line's map of the second half into the whole.
    A Mapper built by hand from the class count records no frame, and the merge refused it."""
    snippet = re.search(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S).group(1)
    _copy_folder(drive, tmp_path / "data/synth/00000", frames=range(0, 3))
    second = _copy_folder(drive, tmp_path / "second", frames=range(3, 6))
    monkeypatch.chdir(tmp_path)
    exec(compile(snippet, "README.md", "exec"), {})
    assert main(["map", str(second), "rellis3d", "--method", "ebs", "--out", "second.npz", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["info", "synth_ebs.npz"]) == 0
    assert json.loads(capsys.readouterr().out)["frame"] == {"name": "odom", "crs": None, "run": read_frame_file(drive).run}
    assert main(["merge", "synth_ebs.npz", "second.npz", "--out", "both.npz"]) == 0
    both = load_map(tmp_path / "both.npz")
    assert both.frame == read_frame_file(drive)
    _assert_same_map(both, _map([drive, "rellis3d"], method="ebs"), evidence_tol=1e-6)
    capsys.readouterr()


def test_maps_and_inputs_of_different_frames_are_refused_naming_both(drive, tmp_path, capsys):
    other = _copy_folder(drive, tmp_path / "elsewhere", frames=range(3, 6), frame_file="name: map\n")
    assert main(["map", str(drive), "--method", "s-csm", "--out", str(tmp_path / "odom.npz"), "--quiet"]) == 0
    assert main(["map", str(other), "--method", "s-csm", "--out", str(tmp_path / "map.npz"), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["merge", str(tmp_path / "odom.npz"), str(tmp_path / "map.npz"), "--out", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "odom.npz" in err and "map.npz" in err and "'odom'" in err and "'map'" in err, err
    assert not (tmp_path / "m.npz").exists()
    assert main(["batch", str(drive), str(other), "--method", "s-csm", "--out", str(tmp_path / "s"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "batch" in err and "'odom'" in err and "'map'" in err and str(other) in err, err
    # the Python API says the same
    with pytest.raises(FrameError, match="'odom'.*'map'"):
        load_map(tmp_path / "odom.npz").merge(load_map(tmp_path / "map.npz"))
    # --frame names a folder's poses frame: then the two merge
    assert main(["map", str(other), "--method", "s-csm", "--frame", "odom", "--out", str(tmp_path / "renamed.npz"), "--quiet"]) == 0
    # (with the first half of the drive: odom.npz holds scans 3-5 too, and a merge refuses to count a scan twice)
    first = _copy_folder(drive, tmp_path / "first", frames=range(0, 3))
    assert main(["map", str(first), "--method", "s-csm", "--out", str(tmp_path / "first.npz"), "--quiet"]) == 0
    # renamed.npz's odom is of a run its folder does not name: one frame only when the user says so
    capsys.readouterr()
    assert main(["merge", str(tmp_path / "first.npz"), str(tmp_path / "renamed.npz"), "--out", str(tmp_path / "m.npz")]) == 2
    assert "of an unknown run" in capsys.readouterr().err and not (tmp_path / "m.npz").exists()
    assert main(["merge", str(tmp_path / "first.npz"), str(tmp_path / "renamed.npz"), "--same-frame", "--out", str(tmp_path / "m.npz")]) == 0
    assert load_map(tmp_path / "m.npz").frame == read_frame_file(drive)  # the first input's run
    capsys.readouterr()


def test_georeferenced_poses_keep_their_coordinates_and_crs(drive, tmp_path, capsys):
    """Survey poses in UTM (500 km east, 4,000 km north): the map sits there, with its CRS, and its
    labels are the local map's shifted by the (lattice-aligned) offset."""
    shift = np.eye(4)
    shift[:3, 3] = [512_000.0, 4_096_000.0, 0.0]  # whole multiples of the 0.2 m voxel
    utm = _copy_folder(drive, tmp_path / "utm", transform=shift, frame_file="name: utm17n\ncrs: EPSG:32617\n")
    assert main(["map", str(utm), "--method", "s-csm", "--out", str(tmp_path / "utm.npz"), "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frame"] == {"name": "utm17n", "crs": "EPSG:32617"}
    far, near = load_map(tmp_path / "utm.npz"), _map([drive])
    assert far.frame == WorldFrame("utm17n", "EPSG:32617")
    assert np.all(np.abs(far.origin - shift[:3, 3]) < 900.0)  # the float64 origin follows the data
    (vf, sf), (vn, sn) = far.voxels(), near.voxels()
    offset = np.round(shift[:3, 3] / 0.2).astype(np.int64)
    shared = {tuple(i) for i in vn.index + offset} & {tuple(i) for i in vf.index}
    assert len(shared) >= 0.999 * len(vn.index)  # poses rounded at 500 km move a face point now and then
    assert main(["info", str(tmp_path / "utm.npz")]) == 0
    assert json.loads(capsys.readouterr().out)["frame"] == {"name": "utm17n", "crs": "EPSG:32617"}
    assert main(["check-data", str(utm)]) == 0
    assert "frame 'utm17n' (EPSG:32617)" in capsys.readouterr().out


def test_points_on_tile_faces_far_away_reach_the_voxel_the_mapper_wrote(tmp_path):
    """The store routes and answers queries with the mapper's own voxel-index arithmetic (relative to
    the origin); the global floor(p / r) it used before disagrees at faces 500 km / 4,000 km out."""
    resolution, tile = 0.2, 4
    rng = np.random.default_rng(3)
    base = np.array([500_000.0, 4_000_000.0, 10.0])
    faces = (np.round(base / (tile * resolution)) + rng.integers(-20, 20, (4000, 3))) * tile * resolution
    faces[:, 2] = rng.uniform(8, 12, len(faces))
    config = load_config(["rellis3d"], method="s-csm").mapping
    mapper = Mapper(config, 9, frame=WorldFrame("utm17n", "EPSG:32617"), workers=1)
    mapper.integrate(faces, rng.integers(1, 9, len(faces)), payload_type="label")
    origin_index = mapper.origin_index
    old = np.floor((faces - mapper.grid_offset_m) / resolution).astype(np.int64)
    shared = voxel_index_of(faces, resolution, mapper.grid_offset_m, origin_index)
    assert np.any(old != shared), "the test needs points where the two arithmetics differ"
    np.testing.assert_array_equal(shared, mapper.query(faces).voxel_index)
    from evsemmap_warp.apps.batch import write_store_from_mapper

    write_store_from_mapper(mapper, tmp_path / "store", tile, ["test"])
    store = MapStore(tmp_path / "store")
    from_store, from_map = store.query(faces), mapper.query(faces)
    np.testing.assert_array_equal(from_store.voxel_index, from_map.voxel_index)
    np.testing.assert_array_equal(from_store.label, from_map.label)
    assert (from_store.label >= 0).all()


def test_frame_and_crs_input_is_checked(drive):
    assert check_crs("epsg:32617") == "EPSG:32617" and check_crs(32617) == "EPSG:32617" and check_crs("") is None
    for bad in ("UTM17N", "EPSG:", "32617", "EPSG:12", "EPSG:0000", "EPSG:01000"):  # codes start at 1024
        with pytest.raises(FrameError, match="not an EPSG code"):
            check_crs(bad)
    with pytest.raises(ConfigError, match="^--crs = 'WGS84 / UTM' is not an EPSG code"):  # the flag, as given
        load_config([str(drive)], crs="WGS84 / UTM")
    with pytest.raises(ConfigError, match="--frame / --crs.*none is named"):
        load_config(["rellis3d"], crs="EPSG:32617")
    with pytest.raises(FrameError):
        WorldFrame("")


def test_bad_frames_and_poses_get_one_line(drive, tmp_path, capsys):
    assert main(["map", str(drive), "--method", "s-csm", "--crs", "UTM17N", "--out", str(tmp_path / "x.npz")]) == 2
    assert "UTM17N" in capsys.readouterr().err
    assert main(["map", str(drive), "--method", "s-csm", "--crs", "EPSG:0000", "--out", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err.strip()  # once recorded as EPSG:0 and refused later, naming neither the flag nor the value
    assert len(err.splitlines()) == 1 and "--crs = 'EPSG:0000'" in err and not (tmp_path / "x.npz").exists(), err
    assert main(["map", str(drive), "--method", "s-csm", "--frame", "first-scan", "--crs", "EPSG:32617", "--out", str(tmp_path / "x.npz")]) == 2
    assert "first-scan" in capsys.readouterr().err
    sheared = _copy_folder(drive, tmp_path / "sheared")
    lines = (sheared / "poses.txt").read_text().splitlines()
    values = lines[2].split()
    values[1] = str(float(values[1]) + 0.3)  # a typo in the rotation: no longer a rigid transform
    lines[2] = " ".join(values)
    (sheared / "poses.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="pose line 3 is not a rigid transform"):
        read_poses(sheared / "poses.txt")
    assert main(["map", str(sheared), "--method", "s-csm", "--out", str(tmp_path / "x.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "poses.txt: pose line 3 is not a rigid transform" in err and len(err.strip().splitlines()) == 1
    broken = _copy_folder(drive, tmp_path / "badframe", frame_file="name: map\ncrs: 4326x\n")
    assert main(["map", str(broken), "--method", "s-csm", "--out", str(tmp_path / "x.npz"), "--quiet"]) == 2
    assert "frame.yaml" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def _write_pcd(path: Path, points: np.ndarray, labels: np.ndarray, viewpoint: np.ndarray) -> None:
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z label\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\n"
              f"VIEWPOINT {viewpoint[0]:.9f} {viewpoint[1]:.9f} {viewpoint[2]:.9f} 1 0 0 0\nPOINTS {len(points)}\nDATA binary\n")
    record = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u4")])
    record["x"], record["y"], record["z"], record["label"] = points[:, 0], points[:, 1], points[:, 2], labels
    path.write_bytes(header.encode() + record.tobytes())


def test_a_log_maps_in_its_fixed_frame_as_the_same_scans_given_there(drive, tmp_path, capsys):
    """A log recorded the usual way (labelled clouds in the sensor frame, TF odom -> base_link ->
    os1_sensor -> os1_lidar with a turned mount): its map is the map of the same scans written as PCD
    files in the fixed frame, not a map in the first cloud's LiDAR frame."""
    pytest.importorskip("rosbags")
    from evsemmap_warp.data.log_writer import write_log
    from evsemmap_warp.data.logs import LogSequence

    log = tmp_path / "drive.bag"
    write_log(drive, log, "rosbag1")
    assert main(["map", str(log), "rellis3d", "rellis3d-bag", "--method", "s-csm", "--out", str(tmp_path / "log.npz"), "--quiet"]) == 0
    capsys.readouterr()
    from_log = load_map(tmp_path / "log.npz")
    # the same scans, placed in odom by the log's own TF, as float32 PCD files
    run = load_config([str(log), "rellis3d-bag"], method="s-csm")
    sequence = LogSequence(run.dataset.resolve_logs(), run.dataset.bag)
    assert from_log.frame == WorldFrame("odom", run=sequence.run_id)  # the log's odom: its run, from its first cloud
    assert not np.allclose(sequence.pose(sequence.frames[0])[:3, :3], np.eye(3))  # a turned mount, a moving robot
    pcd = tmp_path / "pcd"
    pcd.mkdir()
    for scan in open_dataset(run.dataset):
        number = int(scan.name.split("message ")[1].split()[0])
        _write_pcd(pcd / f"scan_{number}.pcd", scan.points, scan.payload, scan.sensor_origin)
    config = tmp_path / "pcd.yaml"
    config.write_text(f"dataset:\n  kind: pcd_sequence\n  paths: [{pcd}]\n  pattern: 'scan_{{index}}.pcd'\n  first_index: 0\n"
                      f"  last_index: {len(sequence.frames) - 1}\n  payload: label\n  num_classes: 9\n  frame: odom\n")
    from_pcd = _map([config, "rellis3d"])
    assert from_pcd.frame == WorldFrame("odom")  # points given in odom: of a run they do not name
    (vl, sl), (vp, sp) = from_log.voxels(), from_pcd.voxels()
    log_cells, pcd_cells = {tuple(i) for i in vl.index}, {tuple(i) for i in vp.index}
    # float32 PCD coordinates move a point sitting within ~1e-6 m of a voxel face now and then
    assert len(log_cells ^ pcd_cells) <= 1e-3 * len(log_cells), len(log_cells ^ pcd_cells)
    shared = np.array(sorted(log_cells & pcd_cells))
    labels_log = from_log.query(from_log.voxel_centers(shared)).label
    labels_pcd = from_pcd.query(from_pcd.voxel_centers(shared)).label
    assert np.mean(labels_log == labels_pcd) >= 0.999
    # and the first-scan convention is still there for a log, in a frame of its own
    assert _map([log, "rellis3d-bag"], frame="first-scan").frame.name == "first-scan of drive.bag"


def test_log_halves_in_one_frame_merge_into_the_whole_drive(drive, tmp_path):
    """Two logs of one drive starting at different places, each mapped on its own and merged, equal
    the drive mapped at once (before, the second half sat where its first cloud's LiDAR frame put it)."""
    pytest.importorskip("rosbags")
    from evsemmap_warp.data.log_writer import write_log

    halves = [tmp_path / "first.bag", tmp_path / "second.bag"]
    write_log(drive, halves[0], "rosbag1", frames=slice(0, 3))
    write_log(drive, halves[1], "rosbag1", frames=slice(3, None))
    whole = _map([*halves, "rellis3d-bag"], method="ebs")
    first, second = _map([halves[0], "rellis3d-bag"], method="ebs"), _map([halves[1], "rellis3d-bag"], method="ebs")
    # each log's odom is of its own run (its first cloud's): one frame only when the caller says so
    with pytest.raises(FrameError, match="odom' of run .* but the second in frame 'odom' of run .*--same-frame"):
        first.merge(second)
    merged = first.merge(second, same_frame=True)
    assert merged.frame == first.frame
    _assert_same_map(whole, merged)
    # batch takes the halves as two inputs: the same check, and the same word to say they are one drive
    from evsemmap_warp.apps.batch import BatchOptions, run_batch
    from evsemmap_warp.core.map_store import MapStore

    inputs = [str(halves[0]), str(halves[1]), "rellis3d-bag"]
    with pytest.raises(FrameError, match="batch: .* of run .*batch --same-frame"):
        run_batch(inputs, BatchOptions(method="ebs", out=tmp_path / "store", executor="inline", progress=False), log=lambda m: None)
    run_batch(inputs, BatchOptions(method="ebs", out=tmp_path / "store", executor="inline", progress=False, same_frame=True),
              log=lambda m: None)
    _assert_same_map(whole, MapStore(tmp_path / "store").to_mapper())
    _assert_same_map(whole, _map([drive], method="ebs"))  # the folder (3x3 rotations) and the logs (quaternions) agree too


def test_merge_of_two_runs_odom_maps_is_refused_naming_both_unless_said_to_share_it(drive, tmp_path, capsys):
    """Two logs' odom frames (REP 105: one run's each) share a name, not coordinates: merge refuses,
    naming both maps and both runs; --same-frame merges them. The run comes from the log, so the
    same command on the same log writes the same bytes."""
    pytest.importorskip("rosbags")
    from evsemmap_warp.data.log_writer import write_log

    maps = []
    for k, frames in enumerate((slice(0, 3), slice(3, None))):
        write_log(drive, tmp_path / f"{k}.bag", "rosbag1", frames=frames)
        maps.append(tmp_path / f"{k}.npz")
        assert main(["map", str(tmp_path / f"{k}.bag"), "rellis3d", "rellis3d-bag", "--method", "ebs", "--out", str(maps[-1]), "--quiet"]) == 0
    capsys.readouterr()
    runs = [load_map(m).frame.run for m in maps]
    assert None not in runs and runs[0] != runs[1]
    assert main(["merge", *map(str, maps), "--out", str(tmp_path / "both.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and all(str(m) in err and r in err for m, r in zip(maps, runs)) and "--same-frame" in err, err
    assert not (tmp_path / "both.npz").exists()
    assert main(["merge", *map(str, maps), "--same-frame", "--out", str(tmp_path / "both.npz")]) == 0
    assert load_map(tmp_path / "both.npz").frame.run == runs[0]
    from evsemmap_warp.apps.viewer import free_port

    capsys.readouterr()
    assert main(["view", *map(str, maps), "--no-serve", "--port", str(free_port())]) == 2  # the viewer's comparison: the same check
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "view together" in err and runs[1] in err, err
    assert main(["view", *map(str, maps), "--same-frame", "--no-serve", "--port", str(free_port())]) == 0
    # playing a drive back: its own map, and one written before maps recorded runs (its scan ids decide); not another run's
    from evsemmap_warp.apps.viewer.drive import open_drive

    old = load_map(maps[0])
    old.frame = WorldFrame("odom")
    old.save(tmp_path / "old.npz")
    for made in (maps[0], tmp_path / "old.npz"):
        open_drive(made, [tmp_path / "0.bag", "rellis3d", "rellis3d-bag"])
    with pytest.raises(FrameError, match=f"play back: .*1.npz is in frame 'odom' of run {runs[1]} but .*0.bag .*in frame 'odom' of run {runs[0]}"):
        open_drive(maps[1], [tmp_path / "0.bag", "rellis3d", "rellis3d-bag"])
    assert main(["map", str(tmp_path / "0.bag"), "rellis3d", "rellis3d-bag", "--method", "ebs", "--out", str(tmp_path / "again.npz"),
                 "--quiet"]) == 0
    assert (tmp_path / "again.npz").read_bytes() == maps[0].read_bytes()
    capsys.readouterr()


def test_maps_with_different_origins_merge_exactly_far_from_zero():
    rng = np.random.default_rng(5)
    base = np.array([500_000.0, 4_000_000.0, 50.0])
    scans = [base + rng.uniform(-40, 40, (3000, 3)) + [400.0 * i, 0, 0] for i in range(2)]  # origins one step apart
    labels = [rng.integers(1, 9, 3000) for _ in scans]
    config = load_config(["rellis3d"], method="s-csm").mapping
    frame = WorldFrame("utm17n", "EPSG:32617")
    whole = Mapper(config, 9, frame=frame, workers=1)
    parts = [Mapper(config, 9, frame=frame, workers=1, origin=scan.mean(axis=0) + [800.0 * i, 0, 0]) for i, scan in enumerate(scans)]
    for scan, label, part in zip(scans, labels, parts):
        whole.integrate(scan, label, payload_type="label")
        part.integrate(scan, label, payload_type="label")
    assert not np.array_equal(parts[0].origin_index, parts[1].origin_index)
    assert np.count_nonzero(whole.voxels()[0].weighted_height_sum) > 1000
    _assert_same_map(whole, parts[0].merge(parts[1]))
