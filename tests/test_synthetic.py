"""The synthetic world: generation, the RELLIS-3D layout it writes, determinism, domains, and that
its cameras, LiDAR, labels and calibration agree with each other."""

import numpy as np
import pytest
import yaml

from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import ConfigError, DatasetConfig, PayloadType, load_config
from evsemmap_warp.data.datasets import open_dataset
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.geometry.projection import ProjectionConfig, label_map_for, project_frames
from evsemmap_warp.data.sequences import Rellis3DSequence, check_sequence
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.scene import generate_world
from evsemmap_warp.synthetic.writer import generate_sequence


@pytest.fixture(scope="session")
def tiny_sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "tiny"
    summary = generate_sequence(load_preset("tiny"), out, progress=False)
    return out, summary


def test_tiny_preset_writes_the_rellis3d_layout(tiny_sequence):
    out, summary = tiny_sequence
    assert summary["frames"] == 6
    for folder, pattern in [("os1_cloud_node_kitti_bin", "*.bin"), ("os1_cloud_node_semantickitti_label_id", "*.label"),
                            ("pylon_camera_node", "*.jpg"), ("pylon_camera_node_label_color", "*.png"), ("pylon_camera_node_label_id", "*.png")]:
        assert len(list((out / folder).glob(pattern))) == 6, folder
    for name in ("poses.txt", "camera_info.txt", "transforms.yaml", "camera_distortion.txt", "synth.yaml"):
        assert (out / name).exists(), name
    assert np.loadtxt(out / "poses.txt").shape == (6, 12)
    record = yaml.safe_load((out / "synth.yaml").read_text())
    assert record["preset"]["name"] == "tiny" and record["preset"]["seed"] == 7
    report = check_sequence(out)
    assert report.ok, report.text()
    assert report.frames == report.with_images == report.with_labels == 6
    raw = np.fromfile(out / "os1_cloud_node_kitti_bin" / "000000.bin", np.float32)
    assert raw.size == 16 * 256 * 4  # every beam and azimuth step, zero returns included


def test_scans_labels_and_images_agree(tiny_sequence):
    """Projecting each scan into its own label image hits pixels of the points' own class: this holds
    the camera model, the extrinsic, the poses and the label writers against one another."""
    out, _ = tiny_sequence
    seq = Rellis3DSequence(out)
    from evsemmap_warp.classes import original_to_v3_table

    table = original_to_v3_table()
    agree = total = 0
    for item in project_frames(seq, seq.frames, label_map_for(seq), ProjectionConfig()):
        own = table[seq.read_point_labels(seq.frames[[f.index for f in seq.frames].index(item.frame_index)])[item.scan_rows]]
        agree += (own == item.values).sum()
        total += len(own)
    assert total > 1000
    assert agree / total > 0.9


def test_generation_is_deterministic_and_domains_change_only_the_look(tmp_path):
    preset = load_preset("tiny", trajectory__frames=2)
    generate_sequence(preset, tmp_path / "a", progress=False)
    generate_sequence(preset, tmp_path / "b", progress=False)
    generate_sequence(load_preset("tiny", trajectory__frames=2, appearance__domain="dusk"), tmp_path / "dusk", progress=False)
    for rel in ("os1_cloud_node_kitti_bin/000001.bin", "pylon_camera_node_label_id/frame000001-1600000000_100.png"):
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes()
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "dusk" / rel).read_bytes()  # same geometry, same labels
    day = Rellis3DSequence(tmp_path / "a")
    dusk = Rellis3DSequence(tmp_path / "dusk")
    difference = np.abs(day.read_image(day.frames[1]).astype(int) - dusk.read_image(dusk.frames[1]).astype(int)).mean()
    assert difference > 20


def test_world_has_every_class_and_per_face_ids():
    world = generate_world(load_preset("default").world, seed=0)
    present = set(np.unique(world.face_v3).tolist())
    assert {0, 2, 3, 4, 5, 6, 7, 8} <= present  # everything but sky, which is what rays miss
    assert len(world.face_material) == len(world.faces)
    mesh = world.mesh()
    assert (mesh.face_attributes["original_id"] == world.face_original_id).all()


def test_bad_presets_name_the_problem(tmp_path):
    with pytest.raises(ConfigError, match="unknown synthetic preset 'nope'"):
        load_preset("nope")
    with pytest.raises(ConfigError, match="appearance.domain must be one of"):
        load_preset("tiny", appearance__domain="winter")
    bad = tmp_path / "bad.yaml"
    bad.write_text("lidar: {beams: 16, rings: 3}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml.lidar: unknown key\(s\) \['rings'\]"):
        load_preset(str(bad))


def test_a_synthetic_sequence_maps_from_its_point_labels(tiny_sequence, tmp_path):
    out, _ = tiny_sequence
    dataset = open_dataset(DatasetConfig(kind="rellis3d", paths=(str(out),), payload=PayloadType.LABEL))
    mapper = Mapper(load_config([], method="s-csm").mapping, dataset.num_classes)
    for scan in dataset:
        mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
    _, summary = mapper.voxels()
    assert mapper.voxel_count > 1000
    assert {4, 7, 8} <= set(np.unique(summary.label).tolist())  # road, grass, vegetation


def test_synth_and_check_data_commands(tmp_path, capsys):
    assert main(["synth", "--world", "tiny", "--frames", "1", "--out", str(tmp_path / "s"), "--quiet"]) == 0
    assert main(["check-data", str(tmp_path / "s")]) == 0
    assert "OK" in capsys.readouterr().out
    (tmp_path / "s" / "camera_info.txt").unlink()
    assert main(["check-data", str(tmp_path / "s")]) == 1
    assert "camera_info.txt: missing" in capsys.readouterr().out


def test_project_and_train_convbki_commands(tiny_sequence, tmp_path, capsys):
    import json

    from evsemmap_warp.classes import remap_ids

    out, _ = tiny_sequence
    assert main(["project", str(out), "--out", str(tmp_path / "gt"), "--overlays", "1"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 6 and report["agreement_with_point_labels_v3"] > 0.9
    assert (tmp_path / "gt" / "ground_truth.npz").exists() and len(list((tmp_path / "gt").glob("overlay_*.png"))) == 1
    assert main(["project", str(out), "--out", str(tmp_path / "depth"), "--overlays", "2", "--color-by", "depth"]) == 0
    capsys.readouterr()
    assert len(list((tmp_path / "depth").glob("overlay_*.png"))) == 2
    # alpha standing in for a network's: evidence 20 on each pixel's true class, at half resolution
    seq = Rellis3DSequence(out)
    (tmp_path / "alpha").mkdir()
    for frame in seq.frames:
        labels = remap_ids(seq.read_label_ids(frame), "t")[::2, ::2]
        alpha = np.ones((9, *labels.shape), np.float16)
        np.put_along_axis(alpha, labels[None], 21.0, axis=0)
        np.save(tmp_path / "alpha" / f"{frame.image.stem}.npy", alpha)
    assert main(["train-convbki", str(out), "--alpha-dir", str(tmp_path / "alpha"), "--out", str(tmp_path / "l.json"),
                 "--window-scans", "3", "--epochs", "2", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["windows"] == 2 and len(result["ell_h"]) == 9
    from evsemmap_warp.methods.convbki import load_lengths

    assert load_lengths(tmp_path / "l.json", 9).horizontal.shape == (9,)
