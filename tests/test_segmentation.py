"""Evidential segmentation: loss values and gradients, the model, datasets and their errors,
metrics, training with checkpoints and resume, inference, and the CLI."""

import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from evsemmap_warp.classes import class_set, decode_color_labels, palette, remap_ids
from evsemmap_warp.apps.cli import main
from evsemmap_warp.segmentation.data import Rellis3DImages, RugdImages, SyntheticOffroad
from evsemmap_warp.segmentation.evidential import dirichlet_from_logits, edl_loss, kl_to_uniform_dirichlet, kl_weight
from evsemmap_warp.segmentation.metrics import SegmentationMetrics
from evsemmap_warp.segmentation.model import ModelConfig, build_model
from evsemmap_warp.segmentation.train import TrainConfig, infer_alpha, load_checkpoint, train

CLASSES = class_set().names
TINY = ModelConfig(width=8, aspp_channels=16)


# ---------------------------------------------------------------------- evidential head and loss
def test_dirichlet_quantities_and_clamp_bounds():
    logits = torch.tensor([[[10.0]], [[-10.0]]]).repeat(1, 1, 1).reshape(1, 2, 1, 1)
    alpha, p, u = dirichlet_from_logits(logits)
    np.testing.assert_allclose(alpha.flatten(), [1 + math.exp(10), 1 + math.exp(-10)], rtol=1e-6)
    np.testing.assert_allclose(u.flatten(), [2 / (2 + math.exp(10) + math.exp(-10))], rtol=1e-6)
    _, _, u9 = dirichlet_from_logits(torch.full((1, 9, 1, 1), 50.0))  # clamped at 10: u = 9 / (9 e^10 + 9)
    np.testing.assert_allclose(float(u9), 9 / (9 * math.exp(10) + 9), rtol=1e-6)
    np.testing.assert_allclose(p.sum(dim=1), 1.0, rtol=1e-6)


def test_kl_against_hand_values():
    # KL(Dir(2, 1) || Dir(1, 1)) = lnG(3) - lnG(2) - lnG(2) - lnG(1) + 1 (psi(2) - psi(3)) = ln 2 - 1/2.
    np.testing.assert_allclose(float(kl_to_uniform_dirichlet(torch.tensor([[2.0, 1.0]]))), math.log(2) - 0.5, rtol=1e-6)
    assert float(kl_to_uniform_dirichlet(torch.ones(1, 5))) == pytest.approx(0.0, abs=1e-6)


def test_edl_loss_hand_value_and_misleading_evidence_removal():
    logits = torch.log(torch.tensor([3.0, 1.0, 0.5])).reshape(1, 3, 1, 1)  # evidence 3, 1, 0.5
    target = torch.tensor([[[0]]])
    loss, parts = edl_loss(logits, target, kl_lambda=0.0)
    assert float(loss) == pytest.approx(math.log(4 + 2 + 1.5) - math.log(4), rel=1e-6)
    _, with_kl = edl_loss(logits, target, kl_lambda=1.0)
    # alpha~ resets the true class: KL(Dir(1, 2, 1.5) || Dir(1)) from the closed form.
    a = torch.tensor([[1.0, 2.0, 1.5]])
    assert with_kl["kl"] == pytest.approx(float(kl_to_uniform_dirichlet(a)), rel=1e-6)


def test_edl_loss_gradient_matches_finite_differences():
    torch.manual_seed(0)
    logits = torch.randn(2, 4, 3, 3, dtype=torch.float64, requires_grad=True)
    target = torch.randint(0, 4, (2, 3, 3))
    assert torch.autograd.gradcheck(lambda x: edl_loss(x, target, 0.37)[0], (logits,), eps=1e-6, atol=1e-6)


def test_kl_schedules():
    assert kl_weight(10, 100) == pytest.approx(0.05) and kl_weight(150, 100) == 0.5
    assert kl_weight(100, 100, "release") == pytest.approx(0.5 * 100 / 60)
    with pytest.raises(ValueError, match="schedule"):
        kl_weight(1, 10, "cosine")


# ---------------------------------------------------------------------- model
@pytest.mark.parametrize("arch", ["r18-os16", "r50-os8"])
def test_model_output_shape(arch):
    model = build_model(ModelConfig(arch=arch, num_classes=9, width=8, aspp_channels=16)).eval()
    with torch.no_grad():
        assert model(torch.zeros(2, 3, 64, 96)).shape == (2, 9, 64, 96)


def test_unknown_arch_and_absent_torchvision():
    with pytest.raises(ValueError, match="arch must be"):
        build_model(ModelConfig(arch="vgg"))
    try:
        import torchvision  # noqa: F401
    except Exception:
        with pytest.raises(ValueError, match="torchvision-r50 needs an importable torchvision"):
            build_model(ModelConfig(arch="torchvision-r50"))


# ---------------------------------------------------------------------- datasets
def test_synthetic_frames_are_seeded_and_cover_the_classes():
    a, b = SyntheticOffroad(50, (64, 128), seed=3), SyntheticOffroad(50, (64, 128), seed=3)
    img, lab = a[7]
    np.testing.assert_array_equal(img, b[7][0])
    assert img.shape == (64, 128, 3) and img.dtype == np.uint8 and lab.shape == (64, 128)
    present = set(np.unique(np.concatenate([a[i][1].ravel() for i in range(50)])))
    assert present == set(range(9))
    assert np.abs(img.astype(int) - SyntheticOffroad(50, (64, 128), domain="dusk", seed=3)[7][0]).mean() > 10
    with pytest.raises(ValueError, match="domain must be one of"):
        SyntheticOffroad(domain="winter")


def _rellis_fixture(root, label_rgb=None, size=(8, 12)):
    seq = root / "00000"
    (seq / "pylon_camera_node").mkdir(parents=True)
    (seq / "pylon_camera_node_label_color").mkdir()
    h, w = size
    Image.fromarray(np.full((h, w, 3), 90, np.uint8)).save(seq / "pylon_camera_node" / "frame000001-1_1.jpg")
    colors = label_rgb if label_rgb is not None else np.zeros((h, w, 3), np.uint8)
    if label_rgb is None:
        colors[:, : w // 2] = (0, 102, 0)  # RELLIS grass (3) -> v3 grass (7)
        colors[:, w // 2 :] = (134, 255, 239)  # RELLIS puddle (31) -> v3 water (2)
    Image.fromarray(colors).save(seq / "pylon_camera_node_label_color" / "frame000001-1_1.png")
    return root


def test_rellis_folder_layout_and_remap(tmp_path):
    ds = Rellis3DImages(_rellis_fixture(tmp_path))
    image, labels = ds[0]
    assert len(ds) == 1 and image.shape == (8, 12, 3)
    assert set(labels[:, :6].ravel()) == {7} and set(labels[:, 6:].ravel()) == {2}


def test_rellis_unknown_color_and_size_mismatch(tmp_path):
    bad = np.zeros((8, 12, 3), np.uint8)
    bad[0, 0] = (1, 2, 3)
    with pytest.raises(ValueError, match=r"1 pixels have colors that are not in the label palette, e.g. \[\(1, 2, 3\)\]"):
        Rellis3DImages(_rellis_fixture(tmp_path / "a", bad))[0]
    with pytest.raises(ValueError, match="is 12x8 but its label"):
        Rellis3DImages(_rellis_fixture(tmp_path / "b", np.zeros((4, 4, 3), np.uint8)))[0]
    with pytest.raises(ValueError, match="no RELLIS-3D frames"):
        Rellis3DImages(tmp_path / "b" / "00000" / "pylon_camera_node")


def test_rugd_layout_with_its_colormap(tmp_path):
    (tmp_path / "RUGD_frames-with-annotations" / "trail").mkdir(parents=True)
    (tmp_path / "RUGD_annotations" / "trail").mkdir(parents=True)
    (tmp_path / "RUGD_annotations" / "RUGD_annotation-colormap.txt").write_text("0 void 0 0 0\n13 mulch 153 76 0\n21 rock 153 204 255\n")
    Image.fromarray(np.full((6, 6, 3), 50, np.uint8)).save(tmp_path / "RUGD_frames-with-annotations" / "trail" / "trail_00001.png")
    lab = np.zeros((6, 6, 3), np.uint8)
    lab[:3] = (153, 76, 0)
    lab[3:] = (153, 204, 255)
    Image.fromarray(lab).save(tmp_path / "RUGD_annotations" / "trail" / "trail_00001.png")
    _, labels = RugdImages(tmp_path)[0]
    assert set(labels[:3].ravel()) == {6} and set(labels[3:].ravel()) == {0}  # mulch -> dirt, rock -> void


def test_remap_tables_and_id_errors():
    assert remap_ids(np.array([0, 1, 3, 4, 10, 18, 31, 33, 29, 32]), "t").tolist() == [0, 6, 7, 8, 4, 0, 2, 6, 7, 2]
    with pytest.raises(ValueError, match=r"label ids \[25, 300\]"):
        remap_ids(np.array([3, 25, 300]), "ids.png")
    assert len(palette("rellis3d_colors")) == 20 + 1 and len(palette("rugd_colors")) == 25  # RELLIS-3D + RUGD gravel for the synthetic trail
    assert decode_color_labels(np.array([[[0, 102, 0]]], np.uint8), palette("rellis3d_colors"), "x").tolist() == [[3]]


def test_non_rgb_images_are_refused(tmp_path):
    root = _rellis_fixture(tmp_path)
    Image.fromarray(np.zeros((8, 12), np.uint8)).save(root / "00000" / "pylon_camera_node" / "frame000001-1_1.jpg")
    with pytest.raises(ValueError, match="expected an RGB image, got mode L"):
        Rellis3DImages(root)[0]


# ---------------------------------------------------------------------- metrics
def test_metrics_on_hand_made_predictions():
    m = SegmentationMetrics(3, bins=2)
    probs = np.array([[[0.9, 0.6, 0.2, 0.2]], [[0.1, 0.4, 0.8, 0.8]], [[0, 0, 0, 0]]], float).transpose(1, 0, 2)  # [1, 3, 4]
    target = np.array([[0, 1, 1, 1]])
    u = np.array([[0.1, 0.9, 0.2, 0.3]])
    m.update(probs, u, target)
    # predictions 0, 0, 1, 1: class 0 IoU 1/2, class 1 IoU 2/3, class 2 absent (left out).
    assert m.miou == pytest.approx((0.5 + 2 / 3) / 2) and m.pixel_accuracy == 0.75 and np.isnan(m.iou[2])
    # bin [0, .5): none; bin [.5, 1]: conf .9 .6 .8 .8 (sum 3.1), correct 3 -> ECE = |3 - 3.1| / 4
    assert m.ece == pytest.approx(0.1 / 4)
    assert m.uncertainty_auroc == 1.0  # the one wrong pixel is the most uncertain
    with pytest.raises(ValueError, match="target ids"):
        m.update(probs, u, np.array([[0, 1, 5, 1]]))


# ---------------------------------------------------------------------- training, checkpoints, inference
def test_train_resume_checkpoint_and_inference(tmp_path):
    src = SyntheticOffroad(24, (32, 64))
    cfg = TrainConfig(model=TINY, input_size=(32, 64), epochs=2, batch_size=4, val_fraction=0.25)
    summary = train(src, CLASSES, cfg, tmp_path / "run", progress=False)
    assert {"miou", "ece", "uncertainty_auroc"} <= set(summary) and summary["epochs_run"] == 2
    for name in ("last.pt", "best.pt", "history.json", "metrics.json", "reliability.png", "uncertainty.png"):
        assert (tmp_path / "run" / name).exists(), name
    model, config, meta, _ = load_checkpoint(tmp_path / "run" / "last.pt", CLASSES)
    assert meta["classes"] == list(CLASSES) and config.input_size == (32, 64) and meta["epoch"] == 2
    # Resume: continues at epoch 3 with the saved optimiser state.
    cfg3 = TrainConfig(model=TINY, input_size=(32, 64), epochs=3, batch_size=4, val_fraction=0.25)
    train(src, CLASSES, cfg3, tmp_path / "run", resume=tmp_path / "run" / "last.pt", progress=False)
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert [h["epoch"] for h in history] == [1, 2, 3]
    with pytest.raises(ValueError, match="already trained for 3 epochs"):
        train(src, CLASSES, cfg3, tmp_path / "run", resume=tmp_path / "run" / "last.pt", progress=False)
    outs = list(infer_alpha(model, config, meta, [src[i][0] for i in range(5)], batch_size=2))
    assert len(outs) == 5 and outs[0][0].shape == (9, 32, 64) and outs[0][0].dtype == np.float16
    assert (outs[0][0].astype(np.float32) >= 1.0).all() and (outs[0][1] <= 1.0).all()


def test_checkpoint_errors(tmp_path):
    src = SyntheticOffroad(12, (32, 64))
    train(src, CLASSES, TrainConfig(model=TINY, input_size=(32, 64), epochs=1, batch_size=4, val_fraction=0.25), tmp_path, progress=False)
    with pytest.raises(ValueError, match="trained for classes"):
        load_checkpoint(tmp_path / "last.pt", ["a", "b"])
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable evsemmap segmentation checkpoint"):
        load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(ValueError, match="outputs but the dataset has"):
        train(src, CLASSES[:4], TrainConfig(model=TINY, input_size=(32, 64), epochs=1), tmp_path / "x", progress=False)


def test_cli_train_and_infer(tmp_path, capsys):
    args = ["train-seg", "--out", str(tmp_path / "run"), "--epochs", "1", "--synthetic-frames", "12", "--input-size", "32", "64",
            "--width", "8", "--aspp-channels", "16", "--batch-size", "4", "--val-fraction", "0.25", "--quiet"]
    assert main(args) == 0
    assert "miou" in json.loads(capsys.readouterr().out)
    images = tmp_path / "images"
    images.mkdir()
    for i in range(3):
        Image.fromarray(SyntheticOffroad(3, (40, 80))[i][0]).save(images / f"f{i}.png")
    assert main(["infer", str(tmp_path / "run" / "last.pt"), str(images), "--out", str(tmp_path / "alpha"), "--quiet"]) == 0
    arrays = sorted((tmp_path / "alpha").glob("*.npy"))
    assert [a.name for a in arrays] == ["f0.npy", "f1.npy", "f2.npy"] and np.load(arrays[0]).shape == (9, 32, 64)
    assert main(["train-seg", "--dataset", "rellis3d", "--out", str(tmp_path / "r")]) == 2
    assert "--data DIR is needed" in capsys.readouterr().err


def test_backbone_weights_load_from_a_given_path_only(tmp_path):
    source = build_model(TINY)
    torch.save(source.backbone.state_dict(), tmp_path / "backbone.pt")
    from evsemmap_warp.segmentation.model import load_backbone_weights

    target = build_model(TINY)
    load_backbone_weights(target, tmp_path / "backbone.pt")
    for key, value in source.backbone.state_dict().items():
        assert torch.equal(value, target.backbone.state_dict()[key])
    torch.save({"stem.0.weight": torch.zeros(1)}, tmp_path / "wrong.pt")
    with pytest.raises(ValueError, match="backbone tensors missing or of another shape"):
        load_backbone_weights(target, tmp_path / "wrong.pt")


def test_eval_seg_on_another_domain_and_caffe_normalisation(tmp_path, capsys):
    cfg = TrainConfig(model=TINY, input_size=(32, 64), epochs=1, batch_size=4, val_fraction=0.25, normalization="caffe")
    train(SyntheticOffroad(12, (32, 64)), CLASSES, cfg, tmp_path / "run", progress=False)
    _, _, meta, _ = load_checkpoint(tmp_path / "run" / "last.pt")
    assert meta["mean"][0] == pytest.approx(103.939 / 255)
    assert main(["eval-seg", str(tmp_path / "run" / "last.pt"), "--domain", "dusk", "--synthetic-frames", "4",
                 "--input-size", "32", "64", "--out", str(tmp_path / "eval")]) == 0
    assert "uncertainty_auroc" in json.loads(capsys.readouterr().out) and (tmp_path / "eval" / "reliability.png").exists()
    with pytest.raises(ValueError, match="normalization must be"):
        TrainConfig(normalization="bgr").validate()
