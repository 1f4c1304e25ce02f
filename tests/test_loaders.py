"""Loaders on small fixture folders in each real layout: RELLIS-3D (sequence layout and loose files),
SemanticKITTI, and plain point files (PCD, PLY, npy, .bin)."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from conftest import TOY_DIR, shared_path
from evsemmap_warp.config import ConfigError, DatasetConfig, PayloadType
from evsemmap_warp.data.datasets import open_dataset
from evsemmap_warp.data.pcd import ExtraColumnsWarning
from evsemmap_warp.data.point_files import read_point_file
from evsemmap_warp.data.sequences import DataError, Rellis3DSequence, SemanticKittiSequence, check_sequence
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence


@pytest.fixture
def synthetic(tmp_path):
    out = tmp_path / "seq"
    generate_sequence(load_preset("tiny", trajectory__frames=2), out, progress=False)
    return out


def test_rellis3d_loose_files_of_the_real_example():
    seq = Rellis3DSequence(shared_path("data", "rellis_example"))
    assert len(seq) == 1 and seq.poses is None
    frame = seq.frames[0]
    assert seq.read_scan(frame).shape == (131072, 4)
    assert seq.camera.width == 1920 and seq.camera.height == 1200 and seq.camera.fx == pytest.approx(2813.643275)
    assert seq.camera.distortion[0] == pytest.approx(-0.134313)  # RELLIS-3D's hard-coded coefficients
    # docs/algorithm.md §2.1: with this extrinsic the LiDAR +x axis points along the camera's -z axis
    np.testing.assert_allclose(seq.lidar_to_camera[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=0.05)
    assert set(np.unique(seq.read_point_labels(frame))) == {0, 3, 4, 17, 18, 19, 23, 31, 33}


def test_check_data_reports_pairing_poses_and_ids(synthetic):
    (synthetic / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")  # one pose for two scans
    label = next((synthetic / "pylon_camera_node_label_id").glob("*.png"))
    from PIL import Image

    ids = np.asarray(Image.open(label)).copy()
    ids[0, 0] = 200  # not an ontology id
    for path in (synthetic / "pylon_camera_node_label_color").glob("*.png"):
        path.unlink()  # fall back to the id images
    Image.fromarray(ids).save(label)
    next((synthetic / "pylon_camera_node").glob("*.jpg")).unlink()
    with open(synthetic / "os1_cloud_node_kitti_bin" / "000001.bin", "ab") as f:
        f.write(b"\0\0\0\0")
    text = check_sequence(synthetic).text()
    assert "poses.txt has 1 lines but scan numbers reach 1" in text
    assert "not a multiple of 16 bytes" in text
    assert "1 scans have no camera image" in text
    assert "label ids outside the ontology: [200]" in text


def test_missing_and_broken_calibration_name_the_file(synthetic):
    (synthetic / "transforms.yaml").write_text("something_else: 1\n")
    with pytest.raises(DataError, match="transforms.yaml: expected os1_cloud_node-pylon_camera_node"):
        Rellis3DSequence(synthetic).lidar_to_camera
    (synthetic / "camera_info.txt").write_text("1 2 3\n")
    with pytest.raises(DataError, match="camera_info.txt: expected four numbers"):
        Rellis3DSequence(synthetic).camera
    with pytest.raises(DataError, match="no scans"):
        Rellis3DSequence(synthetic / "pylon_camera_node")


def write_semantickitti(root):
    rng = np.random.default_rng(0)
    (root / "velodyne").mkdir(parents=True)
    (root / "labels").mkdir()
    raw_ids = np.array([0, 10, 40, 52, 70, 252], np.uint32)
    for i in range(2):
        points = np.concatenate([rng.uniform(-5, 5, (6, 3)), np.ones((6, 1))], 1).astype(np.float32)
        points.tofile(root / "velodyne" / f"{i:06d}.bin")
        (raw_ids | (np.uint32(7) << np.uint32(16))).tofile(root / "labels" / f"{i:06d}.label")  # instance ids above bit 16
    tr = np.array([[0, -1, 0, 0.1], [0, 0, -1, 0.2], [1, 0, 0, 0.3]], float)
    (root / "calib.txt").write_text("P0: " + " ".join(["0"] * 12) + "\nTr: " + " ".join(map(str, tr.ravel())) + "\n")
    cam_poses = [np.eye(4), np.eye(4)]
    cam_poses[1][:3, 3] = [0, 0, 2.0]  # 2 m forward along the camera's z
    np.savetxt(root / "poses.txt", np.array([p[:3].ravel() for p in cam_poses]))
    return tr


def test_semantickitti_sequence_poses_and_learning_map(tmp_path):
    root = tmp_path / "sequences" / "00"
    write_semantickitti(root)
    seq = SemanticKittiSequence(root)
    assert len(seq) == 2
    # LiDAR pose = inv(Tr) pose Tr: the camera's +z is the LiDAR's +x, so scan 1 sits 2 m ahead in x
    np.testing.assert_allclose(seq.pose(seq.frames[1])[:3, 3], [2, 0, 0], atol=1e-12)
    dataset = open_dataset(DatasetConfig(kind="semantickitti", paths=(str(root),)))
    scans = list(dataset)
    assert scans[0].payload.tolist() == [0, 1, 9, 0, 15, 1]  # unlabeled, car, road, other-structure, vegetation, moving car
    np.testing.assert_allclose(scans[1].sensor_origin, [2, 0, 0], atol=1e-12)


def test_rellis3d_dataset_rejects_non_label_payloads(synthetic):
    with pytest.raises(ConfigError, match="mapped from its per-point labels"):
        open_dataset(DatasetConfig(kind="rellis3d", paths=(str(synthetic),), payload=PayloadType.ALPHA))


def test_point_files_of_every_kind(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (10, 3))
    with pytest.warns(ExtraColumnsWarning):  # the toy scans carry one undeclared column
        pcd = read_point_file(TOY_DIR / "sim_unstructured_annotated_1.pcd")
    assert pcd.points.shape[1] == 3 and "label" in pcd.fields
    cloud = trimesh.PointCloud(xyz)
    cloud.vertex_attributes = {"label": np.arange(10, dtype=np.float32)}
    cloud.export(tmp_path / "a.ply")
    ply = read_point_file(tmp_path / "a.ply")
    np.testing.assert_allclose(ply.points, xyz, rtol=1e-6)
    assert ply.fields["label"].tolist() == list(range(10))
    np.save(tmp_path / "a.npy", np.concatenate([xyz, np.ones((10, 9))], 1))
    assert read_point_file(tmp_path / "a.npy").fields["values"].shape == (10, 9)
    np.concatenate([xyz, np.zeros((10, 1))], 1).astype(np.float32).tofile(tmp_path / "a.bin")
    assert read_point_file(tmp_path / "a.bin").points.shape == (10, 3)
    with open(tmp_path / "a.bin", "ab") as f:
        f.write(b"\0" * 4)
    with pytest.raises(ValueError, match="a.bin.*truncated"):
        read_point_file(tmp_path / "a.bin")
    bad = xyz.copy()
    bad[3, 1] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(ValueError, match="nan.npy: 1 of 10 points have NaN.*row 3"):
        read_point_file(tmp_path / "nan.npy")
    (tmp_path / "a.xyz").write_text("0 0 0\n")
    with pytest.raises(ValueError, match="unknown point file type '.xyz'"):
        read_point_file(tmp_path / "a.xyz")
    (tmp_path / "broken.ply").write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nend_header\n1\n")
    with pytest.raises(ValueError, match="broken.ply"):
        read_point_file(tmp_path / "broken.ply")


def test_the_toy_scans_extra_column_warning_comes_once_per_dataset():
    import warnings

    from evsemmap_warp.config import load_config

    run = load_config([Path(__file__).resolve().parents[1] / "configs/datasets/sbki_toy.yaml"], method="s-bki")
    dataset = open_dataset(run.dataset)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):
            assert sum(1 for _ in dataset) == 12
    extra = [w for w in caught if issubclass(w.category, ExtraColumnsWarning)]
    assert len(extra) == 1, [str(w.message) for w in extra]
    assert "sim_unstructured_annotated_1.pcd" in str(extra[0].message)
