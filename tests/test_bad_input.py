"""Bad input, one case per row: the CLI answers with one line that names the file, key or value and
exit code 2, never a traceback; the library raises a ValueError saying the same. Each case was a crash,
a hang or a silently wrong result once (the outside trial's list)."""

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import ConfigError, MappingConfig, load_config
from evsemmap_warp.core.map_file import MAGIC, MapFileError
from evsemmap_warp.core.mapper import Mapper, load_map
from evsemmap_warp.data.point_files import read_point_file

REPO = Path(__file__).resolve().parents[1]
PRESET = REPO / "configs/presets/offroad.yaml"


# ------------------------------------------------------------------------------------- configs
CONFIG_CASES = {
    "not-a-mapping": ("- 1\n- 2\n", "expected a mapping"),
    "nan-resolution": ("mapping:\n  resolution_m: .nan\n", "resolution_m.*finite"),
    "inf-length": ("mapping:\n  length_m: .inf\n", "length_m.*finite"),
    "negative-resolution": ("mapping:\n  resolution_m: -0.2\n", "resolution_m.*> 0"),
    "zero-length": ("mapping:\n  length_m: 0\n", "length_m.*> 0"),
    "threshold-above-one": ("mapping:\n  uncertainty_drop_fraction: 1.5\n", r"uncertainty_drop_fraction.*\[0, 1\)"),
    "threshold-negative": ("mapping:\n  uncertainty_drop_fraction: -0.1\n", "uncertainty_drop_fraction"),
    "integer-key": ("mapping:\n  1: 2\n", "key 1 .*not a name"),
    "integer-section": ("1:\n  resolution_m: 0.2\n", "not a section name"),
    "string-for-number": ("mapping:\n  resolution_m: fine\n", "resolution_m = 'fine'"),
    "list-for-string": ("mapping:\n  convbki:\n    lengths_file: [1, 2]\n", r"mapping.convbki: lengths_file = \[1, 2\]"),
    "unknown-section-key": ("mapping:\n  sbki:\n    depth: 3\n", "unknown key mapping.sbki.depth"),
    "section-not-a-mapping": ("mapping:\n  sbki: 3\n", "mapping.sbki must be a mapping"),
    "bool-for-number": ("mapping:\n  sigma0: true\n", "sigma0"),
    "section-not-mapping": ("mapping: 3\n", "section 'mapping' must be a mapping"),
    "unknown-key": ("mapping:\n  resolution: 0.2\n", "unknown key mapping.resolution"),
    "kernel-too-long": ("mapping:\n  length_m: 50\n  resolution_m: 0.2\n", "visit about [0-9,]+ voxels"),
    "broken-yaml": ("mapping: [1, 2\n", "not valid YAML"),
}


@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_bad_config_is_one_line_naming_file_and_key(tmp_path, capsys, case):
    text, pattern = CONFIG_CASES[case]
    path = tmp_path / f"{case}.yaml"
    path.write_text(text)
    line = run_cli(capsys, "dump-config", PRESET, path, "--method", "ebs")
    assert str(path) in line
    import re

    assert re.search(pattern, line), line


def test_a_kernel_that_would_run_for_hours_is_refused_with_the_estimate():
    with pytest.raises(ConfigError, match=r"65,[0-9]{3},[0-9]{3} voxels"):
        MappingConfig(length_m=50.0, resolution_m=0.2, adaptive_length=False)
    # the paper's lengths stay far below the limit
    assert load_config([PRESET], method="ebs").mapping.voxels_per_point() < 1000


def test_free_space_rays_from_a_far_sensor_origin_are_refused():
    cfg = load_config([PRESET], method="s-bki").mapping
    from evsemmap_warp.config import Compat

    mapper = Mapper(cfg.replace(compat=Compat.SBKI, sbki={"free_resolution_m": 0.5}), 3)
    pts = np.random.default_rng(0).uniform(-5, 5, (2000, 3))
    with pytest.raises(ValueError, match=r"free-space rays would place about .* set mapping.sbki.max_range_m"):
        mapper.integrate(pts, np.zeros(2000, np.int64), payload_type="label", sensor_origin=[5e6, 0, 0])
    assert mapper.voxel_count == 0


# ------------------------------------------------------------------------------------- point files
def _pcd(header_points="3", size="4 4 4", count="1 1 1", width="3", data=b"", kind="binary"):
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE {size}\nTYPE F F F\nCOUNT {count}\nWIDTH {width}\nHEIGHT 1\n"
            f"POINTS {header_points}\nDATA {kind}\n").encode()
    return head + data


_THREE_POINTS = np.arange(9, dtype=np.float32).tobytes()
POINT_FILE_CASES = {
    "bin-not-multiple-of-16.bin": (np.arange(9, dtype=np.float32).tobytes(), "not a whole number of 16-byte"),
    "pcd-negative-points.pcd": (_pcd(header_points="-3", width="-3", data=_THREE_POINTS), "negative"),
    "pcd-too-few-points.pcd": (_pcd(header_points="2", width="2", data=_THREE_POINTS), "header declares 2 points"),
    "pcd-too-many-points.pcd": (_pcd(header_points="5", width="5", data=_THREE_POINTS), "truncated binary data"),
    "pcd-width-disagrees.pcd": (_pcd(width="7", data=_THREE_POINTS), "WIDTH x HEIGHT = 7"),
    "pcd-wrong-size.pcd": (_pcd(size="4 4 2", data=_THREE_POINTS), "unsupported TYPE F SIZE 2"),
    "pcd-zero-count.pcd": (_pcd(count="1 0 1", data=_THREE_POINTS), "COUNT entries must be >= 1"),
    "pcd-ascii-extra-rows.pcd": (_pcd(header_points="1", width="1", kind="ascii", data=b"0 0 0\n1 1 1\n"), "2 data rows"),
    "empty.npy": (b"", "empty file"),
    "ply-nan.ply": (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
                    b"0 0 0\nnan 1 1\n", "NaN or inf"),
}


@pytest.mark.parametrize("name", sorted(POINT_FILE_CASES))
def test_bad_point_file_is_refused_naming_it(tmp_path, capsys, name):
    data, pattern = POINT_FILE_CASES[name]
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(ValueError, match=pattern):
        read_point_file(path)
    line = run_cli(capsys, "view", _small_map_file(tmp_path), "--scan", path, "--no-serve")
    assert str(path) in line


def test_npz_renamed_npy_and_npy_renamed_npz(tmp_path, capsys):
    npz_as_npy = tmp_path / "points.npy"
    with open(npz_as_npy, "wb") as f:
        np.savez(f, points=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="is an .npz archive"):
        read_point_file(npz_as_npy)
    npy_as_npz = tmp_path / "map.npz"
    with open(npy_as_npz, "wb") as f:
        np.save(f, np.zeros((3, 3)))
    line = run_cli(capsys, "info", npy_as_npz)
    assert str(npy_as_npz) in line and "not an evsemmap map file" in line


# ------------------------------------------------------------------------------------- map files
def _small_map_file(tmp_path) -> Path:
    """A small map file (made once per test)."""
    path = tmp_path / "small.npz"
    if not path.exists():
        rng = np.random.default_rng(0)
        mapper = Mapper(load_config([PRESET], method="ebs").mapping, 3)
        mapper.integrate(rng.uniform(-2, 2, (300, 3)), rng.gamma(1, 3, (300, 3)) + 1, payload_type="alpha")
        mapper.save(path)
    return path


def _parts(path: Path) -> tuple[dict, bytes]:
    """A map file's header and payload."""
    data = path.read_bytes()
    length = int.from_bytes(data[len(MAGIC):len(MAGIC) + 4], "little")
    start = len(MAGIC) + 4
    return json.loads(data[start:start + length]), data[start + length:]


def _rewrite(src: Path, dst: Path, header: dict, meta: dict) -> Path:
    """``src`` with header keys and meta keys replaced (a meta value None: the key removed); the payload and its checks stay."""
    head, payload = _parts(src)
    head |= header
    for key, value in meta.items():
        if value is None:
            head["meta"].pop(key)
        else:
            head["meta"][key] = value
    assert head["payload_crc32"] == zlib.crc32(payload)
    text = json.dumps(head, sort_keys=True).encode()
    dst.write_bytes(MAGIC + struct.pack("<I", len(text)) + text + payload)
    return dst


# (header changes, meta changes, what the one line says); damaged payloads: tests/test_map_file.py's V3_CASES
MAP_FILE_CASES = {
    "index-out-of-range": ({"index_low": [1 << 22, 0, 0]}, {}, "outside the key range"),
    "resolution-disagrees": ({"resolution": 0.5}, {}, "disagrees with meta.mapping.resolution_m"),
    "missing-meta-key": ({}, {"num_classes": None}, "meta lacks the key 'num_classes'"),
    "wrong-meta-type": ({}, {"scans_integrated": "many"}, "meta.scans_integrated = 'many' has the wrong type"),
    "origin-off-lattice": ({"origin": [0.05, 0.0, 0.0]}, {}, "not on the voxel lattice"),
    "unknown-mapping-key": ({}, {"mapping": "+warp_speed"}, "unknown key"),
    "old-mapping-key": ({}, {"mapping": "+block_depth"}, r"unknown key\(s\) \['block_depth'\]"),
}


@pytest.mark.parametrize("case", sorted(MAP_FILE_CASES))
def test_inconsistent_map_file_is_refused_on_load(tmp_path, capsys, case):
    header, meta, pattern = MAP_FILE_CASES[case]
    src = _small_map_file(tmp_path)
    if meta.get("mapping", "").startswith("+"):  # a key the mapping section does not have
        meta = {"mapping": _parts(src)[0]["meta"]["mapping"] | {meta["mapping"][1:]: 9}}
    bad = _rewrite(src, tmp_path / f"{case}.npz", header, meta)
    with pytest.raises(MapFileError, match=pattern):
        load_map(bad)
    line = run_cli(capsys, "info", bad)
    assert str(bad) in line


def test_a_damaged_version_3_map_file_is_one_line(tmp_path, capsys):
    data = _small_map_file(tmp_path).read_bytes()
    for name, damaged in (("cut.npz", data[:len(data) - 50]), ("flipped.npz", data[:-30] + bytes([data[-30] ^ 0xFF]) + data[-29:])):
        (tmp_path / name).write_bytes(damaged)
        line = run_cli(capsys, "info", tmp_path / name)
        assert str(tmp_path / name) in line and ("truncated" in line or "checksum mismatch" in line)


# ------------------------------------------------------------------------------------- checkpoints
@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    import torch

    from evsemmap_warp.segmentation.config import ModelConfig
    from evsemmap_warp.segmentation.model import build_model
    from evsemmap_warp.segmentation.train import TrainConfig, save_checkpoint

    config = TrainConfig(model=ModelConfig(num_classes=3, width=8, aspp_channels=8), input_size=(32, 64))
    model = build_model(config.model)
    path = tmp_path_factory.mktemp("ckpt") / "good.pt"
    save_checkpoint(path, model, torch.optim.SGD(model.parameters(), lr=0.1), 1, config, ["a", "b", "c"], [])
    return path


def _tampered_checkpoint(src: Path, dst: Path, how: str) -> Path:
    import torch

    ckpt = torch.load(src, weights_only=True)
    cfg = json.loads(ckpt["meta"]["train_config"])
    if how == "unknown-key":
        cfg["warp_factor"] = 9
    elif how == "other-shape":
        cfg["model"]["width"] = 16
    ckpt["meta"]["train_config"] = json.dumps(cfg)
    torch.save(ckpt, dst)
    return dst


@pytest.mark.parametrize("how,pattern", [("unknown-key", "training config does not fit"),
                                          ("other-shape", "weights do not fit"),
                                          ("not-a-checkpoint", "not a readable evsemmap segmentation checkpoint")])
def test_bad_checkpoint_is_one_line(tmp_path, capsys, checkpoint, how, pattern):
    if how == "not-a-checkpoint":
        bad = tmp_path / "junk.pt"
        bad.write_bytes(b"this is not a checkpoint")
    else:
        bad = _tampered_checkpoint(checkpoint, tmp_path / f"{how}.pt", how)
    from PIL import Image

    Image.fromarray(np.zeros((32, 64, 3), np.uint8)).save(tmp_path / "img.png")
    line = run_cli(capsys, "infer", bad, tmp_path / "img.png", "--out", tmp_path / "out")
    assert str(bad) in line and pattern in line


# ------------------------------------------------------------------------------------- flags
@pytest.mark.parametrize("argv,pattern", [
    (["view", "{map}", "--port", "99999"], "port 99999 is outside"),
    (["view", "{map}", "--max-voxels", "-5"], "--max-voxels: -5"),
    (["project", "{tmp}", "--out", "{tmp}/o", "--max-frames", "-1"], "--max-frames: -1"),
    (["map", "{preset}", "--method", "ebs", "--out", "{tmp}/m.npz", "--workers", "0"], "--workers: 0"),
    (["train-seg", "--out", "{tmp}/o", "--lr", "nan"], "--lr: nan"),
])
def test_bad_flag_values_are_one_line(tmp_path, capsys, argv, pattern):
    argv = [a.format(map=_small_map_file(tmp_path), tmp=tmp_path, preset=PRESET) for a in argv]
    assert pattern in run_cli(capsys, *argv)


def test_project_refuses_images_of_another_size_than_the_camera(tmp_path, capsys):
    from PIL import Image

    from evsemmap_warp.synthetic.preset import load_preset
    from evsemmap_warp.synthetic.writer import generate_sequence

    seq = tmp_path / "seq"
    generate_sequence(load_preset("tiny"), seq, progress=False)
    from evsemmap_warp.data.sequences import Rellis3DSequence

    label = Rellis3DSequence(seq).frames[1].label_image
    with Image.open(label) as img:
        img.resize((img.width // 2, img.height // 2), Image.NEAREST).save(label)
    line = run_cli(capsys, "project", seq, "--out", tmp_path / "gt")
    assert str(label) in line and "but the sequence's camera" in line


@pytest.mark.parametrize("text,pattern", [
    ("- 1\n", "expected a mapping of sections"),
    ("networks:\n  a: {epochs: .nan}\n", "epochs = nan must be a finite number"),
    ("projection: {fov_margin_deg: 400}\n", "fov_margin_deg must lie in"),
    ("networks:\n  a: {train_on: [s], epochs: 2}\nsequences:\n  s: {world: tiny, frames: -3}\n", "frames"),
])
def test_bad_experiment_config_is_one_line(tmp_path, capsys, text, pattern):
    path = tmp_path / "study.yaml"
    path.write_text(text)
    line = run_cli(capsys, "experiment", path, "--out", tmp_path / "out")
    assert str(path) in line and pattern in line


# ------------------------------------------------------------------------------------- sequences
@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    from evsemmap_warp.synthetic.preset import load_preset
    from evsemmap_warp.synthetic.writer import generate_sequence

    root = tmp_path_factory.mktemp("seq") / "base"
    generate_sequence(load_preset("tiny"), root, progress=False)
    return root


def _first(folder: Path, pattern: str) -> Path:
    return sorted(folder.glob(pattern))[0]


def _truncate(path: Path, nbytes: int) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:-nbytes])


def _poke_floats(path: Path, dtype, rows: dict) -> None:
    values = np.fromfile(path, dtype=dtype)
    for i, v in rows.items():
        values[i] = v
    values.tofile(path)


SEQUENCE_CASES = {
    "truncated-scan": (lambda s: _truncate(_first(s, "os1_cloud_node_kitti_bin/*.bin"), 5), "map", "not a whole number of 16-byte"),
    "short-label-file": (lambda s: _truncate(_first(s, "os1_cloud_node_semantickitti_label_id/*.label"), 8), "map", "labels for a scan of"),
    "poses-run-short": (lambda s: (s / "poses.txt").write_text("\n".join((s / "poses.txt").read_text().splitlines()[:2]) + "\n"), "map", "2 poses, but scan 2"),
    "nan-pose": (lambda s: (s / "poses.txt").write_text("nan 0 0 0 0 1 0 0 0 0 1 0\n" + "\n".join((s / "poses.txt").read_text().splitlines()[1:]) + "\n"), "map", "has NaN or inf"),
    "label-ids-outside-table": (lambda s: _poke_floats(_first(s, "os1_cloud_node_semantickitti_label_id/*.label"), np.uint32, {0: 999}), "map", "outside the class table: [999]"),
    "label-ids-outside-table-project": (lambda s: _poke_floats(_first(s, "os1_cloud_node_semantickitti_label_id/*.label"), np.uint32, {0: 999}), "project", "outside the class table: [999]"),
    "nan-scan-point": (lambda s: _poke_floats(_first(s, "os1_cloud_node_kitti_bin/*.bin"), np.float32, {0: np.nan}), "map", "NaN or inf coordinates"),
    "binary-camera-info": (lambda s: (s / "camera_info.txt").write_bytes(bytes(range(128, 256))), "project", "camera_info.txt: not a text file"),
    "binary-transforms": (lambda s: (s / "transforms.yaml").write_bytes(bytes(range(128, 256))), "project", "transforms.yaml: not a text file"),
    "broken-image": (lambda s: _first(s, "pylon_camera_node/*.jpg").write_bytes(b"not a jpeg"), "project", "pylon_camera_node/"),
}


@pytest.mark.parametrize("case", sorted(SEQUENCE_CASES))
def test_broken_sequence_is_one_line_naming_the_file(tmp_path, capsys, tiny_sequence, case):
    import shutil

    damage, command, pattern = SEQUENCE_CASES[case]
    seq = tmp_path / "seq"
    shutil.copytree(tiny_sequence, seq)
    damage(seq)
    argv = ["map", seq, "--method", "ebs", "--out", tmp_path / "m.npz", "--quiet"] if command == "map" else ["project", seq, "--out", tmp_path / "gt"]
    line = run_cli(capsys, *argv)
    assert str(seq) in line and pattern in line, line


@pytest.mark.parametrize("argv,pattern", [
    (["map", "{junk}", "--method", "ebs", "--out", "{tmp}/m.npz"], "not a text file"),
    (["experiment", "{junk}"], "not a text file"),
    (["synth", "--world", "{junk}", "--out", "{tmp}/s"], "not a text file"),
    (["view", "{map}", "--trajectory", "{junk}", "--no-serve"], "not a table of numbers"),
    (["view", "{map}", "--host", "999.1.1.1", "--no-serve"], "cannot serve on host '999.1.1.1'"),
])
def test_binary_junk_and_unusable_hosts_are_one_line(tmp_path, capsys, argv, pattern):
    junk = tmp_path / "junk.yaml"
    junk.write_bytes(bytes(range(128, 256)) * 4)
    argv = [a.format(junk=junk, tmp=tmp_path, map=_small_map_file(tmp_path)) for a in argv]
    assert pattern in run_cli(capsys, *argv)


# ------------------------------------------------------------------------------------- issue 31: the crash list
def _payload_cases():
    pts = np.random.default_rng(0).normal(size=(50, 3))
    cases = {
        "labels-as-strings": (pts, np.array(["a"] * 50), "label", "holds strings"),
        "labels-as-objects": (pts, np.array([1] * 50, dtype=object), "label", "Python objects"),
        "labels-ragged": (pts, [[1], [1, 2]] + [[1]] * 48, "label", "cannot be read as an array"),
        "alpha-as-objects": (pts, np.full((50, 3), 2.0).astype(object), "alpha", "Python objects"),
        "alpha-complex": (pts, np.full((50, 3), 2.0 + 1j), "alpha", "complex numbers"),
        "points-complex": (pts + 0j, np.ones(50, np.int64), "label", "points: holds complex"),
        "coordinate-1.7e308": (np.vstack([[1.7e308, 0, 0], pts[1:]]), np.ones(50, np.int64), "label", "farther than 1e\\+12 m"),
    }
    return cases


@pytest.mark.parametrize("case", sorted(_payload_cases()))
def test_api_payloads_that_crashed_are_a_value_error(case):
    points, payload, payload_type, pattern = _payload_cases()[case]
    mapper = Mapper(load_config([PRESET], method="ebs").mapping, 3, workers=1)
    with pytest.raises(ValueError, match=pattern):
        mapper.integrate(points, payload, payload_type=payload_type)
    assert mapper.scans_integrated == 0 and mapper.voxel_count == 0 and mapper.origin_index is None


def test_a_torch_tensor_that_requires_grad_is_read_as_its_values():
    torch = pytest.importorskip("torch")
    pts = np.random.default_rng(0).normal(size=(50, 3))
    alpha = np.full((50, 3), 2.0)
    a, b = (Mapper(load_config([PRESET], method="ebs").mapping, 3, workers=1) for _ in range(2))
    a.integrate(pts, alpha, payload_type="alpha")
    b.integrate(torch.tensor(pts, requires_grad=True), torch.tensor(alpha, requires_grad=True), payload_type="alpha")
    np.testing.assert_array_equal(a.voxels()[0].evidence, b.voxels()[0].evidence)
    np.testing.assert_array_equal(a.query(pts).label, b.query(torch.tensor(pts, requires_grad=True)).label)


def test_free_space_rays_from_a_far_origin_with_few_points_are_refused_not_run_out_of_memory():
    """Two points 90,000 km from the sensor origin pass the sample estimate (45 M); the float32 step
    list along the ray then never ended (killed by the OOM killer at 23 GB)."""
    from evsemmap_warp.config import Compat

    cfg = load_config([PRESET], method="s-bki").mapping.replace(compat=Compat.SBKI, sbki={"max_range_m": None})
    mapper = Mapper(cfg, 3, workers=1)
    with pytest.raises(ValueError, match=r"a ray of [0-9,]+ steps, at most 4,194,304 along one ray.*set mapping.sbki.max_range_m"):
        mapper.integrate(np.zeros((2, 3)), np.zeros(2, np.int64), payload_type="label", sensor_origin=[9e7, 0, 0])
    assert mapper.voxel_count == 0 and mapper.scans_integrated == 0


def test_config_and_input_paths_that_crashed_are_one_line(tmp_path, capsys, tiny_sequence):
    import shutil

    bad = tmp_path / "p123.yaml"
    bad.write_text("dataset:\n  kind: rellis3d\n  paths: [123]\n")
    assert "paths = [123] is not a valid tuple[str, ...]" in run_cli(capsys, "map", bad, "--method", "ebs", "--out", tmp_path / "m.npz")
    # a path that does not exist is no preset name: named as a path, never "available: " and nothing
    line = run_cli(capsys, "map", tmp_path / "nope" / "seq", "--method", "ebs", "--out", tmp_path / "m.npz")
    assert line.endswith("nope/seq: no such file or folder"), line
    assert "available: offroad, release, rellis3d, rellis3d-bag" in run_cli(capsys, "map", "nopreset", "--method", "ebs", "--out", tmp_path / "m.npz")
    # check-data of a missing folder is a problem (exit 1), not silence and exit 0
    assert main(["check-data", str(tmp_path / "nope" / "seq")]) == 1
    assert "no such sequence folder" in capsys.readouterr().out
    assert "is a sequence folder or a robot log" in run_cli(capsys, "check-data", "rellis3d")
    # a folder of maps (or a store) is no sequence folder
    maps = tmp_path / "maps"
    maps.mkdir()
    shutil.copy(_small_map_file(tmp_path), maps / "a.npz")
    assert "not a sequence folder (it holds map files" in run_cli(capsys, "dump-config", maps)
    # a complex .npy keeps no silent imaginary part
    np.save(tmp_path / "scan.npy", np.ones((10, 3), complex))
    with pytest.raises(ValueError, match="holds complex128 values"):
        read_point_file(tmp_path / "scan.npy")


def test_a_bad_camera_info_is_listed_once_by_check_data(tmp_path, capsys, tiny_sequence):
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(tiny_sequence, seq)
    (seq / "camera_info.txt").write_text("nan 100 50 50\n")
    assert main(["check-data", str(seq), str(tiny_sequence)]) == 1
    out = capsys.readouterr().out
    assert out.count("camera_info.txt: fx fy cx cy = ['nan', '100', '50', '50']: the focal lengths must be finite") == 1, out
    assert f"{tiny_sequence}: 6 scans" in out  # the next folder is still checked


def test_singular_poses_and_calibrations_are_named(tmp_path):
    from evsemmap_warp.data.sequences import DataError, SemanticKittiSequence, read_poses
    from evsemmap_warp.geometry.transform_tree import TransformError, TransformTree

    poses = tmp_path / "poses.txt"
    poses.write_text("0 0 0 0 0 0 0 0 0 0 0 0\n1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DataError, match="poses.txt: pose line 1 is not a rigid transform: its rotation is singular"):
        read_poses(poses)
    kitti = tmp_path / "kitti"
    (kitti / "velodyne").mkdir(parents=True)
    np.zeros((4, 4), np.float32).tofile(kitti / "velodyne" / "000000.bin")
    (kitti / "calib.txt").write_text("Tr: " + " ".join(["0"] * 12) + "\n")
    with pytest.raises(DataError, match="calib.txt: Tr is not a rigid transform"):
        SemanticKittiSequence(kitti)
    tree = TransformTree()
    with pytest.raises(TransformError, match="'odom' -> 'base' at t = 5.000000000 s is no rigid transform|'odom' -> 'base' at t = 5"):
        tree.add_timed("odom", "base", 5_000_000_000, [0, 0, 0], [0, 0, 0, 0])


def test_the_worker_advice_fits(monkeypatch):
    import re

    from evsemmap_warp.apps.batch import BatchOptions, check_memory, planning

    monkeypatch.setattr(planning, "available_memory", lambda: 22 * 2**30)
    with pytest.raises(ConfigError, match=r"use fewer --workers \(at most \d+ fit") as refused:
        check_memory(BatchOptions(method="ebs", out="x", chunk_frames=1), 1000, 1, 13304, 20000, 9, automatic=True)
    fitting = int(re.search(r"at most (\d+) fit", str(refused.value)).group(1))
    check_memory(BatchOptions(method="ebs", out="x", chunk_frames=1), fitting, 1, 13304, 20000, 9)
