"""Projection (docs/algorithm.md §2) against hand-computed pixels, torch's bilinear upsampling, and one real
RELLIS-3D frame."""

import numpy as np
import pytest
import torch

from conftest import shared_path
from evsemmap_warp.geometry.camera import PinholeCamera, matrix_to_quaternion, quaternion_to_matrix
from evsemmap_warp.classes import original_to_v3_table
from evsemmap_warp.geometry.projection import Bin, ProjectedFrame, ProjectionConfig, bin_frames, project_scan, sample_map
from evsemmap_warp.data.sequences import Rellis3DSequence

CAMERA = PinholeCamera(100.0, 100.0, 50.0, 40.0, 100, 80)


def test_hand_computed_pixels_and_rejections():
    points = np.array([
        [0.1, 0.2, 1.0],  # -> (60, 60)
        [0.0, 0.0, 2.0],  # -> the principal point (50, 40)
        [0.0, 0.0, -2.0],  # behind the camera
        [0.0, 0.0, 0.0],  # a zero return
        [0.5, 0.0, 1.0],  # u = 100: just outside the image (0 <= u < width)
        [-0.5, -0.4, 1.0],  # u = 0, v = 0: the first pixel
        [5.0, 0.0, 1.0],  # far outside the angle of view
    ])
    projected = project_scan(points, CAMERA, np.eye(4))
    assert projected.index.tolist() == [0, 1, 5]
    np.testing.assert_allclose(projected.pixel, [[60, 60], [50, 40], [0, 0]], atol=1e-9)
    np.testing.assert_allclose(projected.depth, [1, 2, 1])


def test_distortion_follows_the_opencv_model():
    camera = PinholeCamera(100.0, 100.0, 50.0, 40.0, 100, 80, (0.1, 0.0, 0.0, 0.0, 0.0))
    # x = 0.1, y = 0.2: r^2 = 0.05, radial factor 1.005
    np.testing.assert_allclose(camera.project(np.array([[0.1, 0.2, 1.0]])), [[60.05, 60.1]], atol=1e-9)
    tangential = PinholeCamera(100.0, 100.0, 50.0, 40.0, 100, 80, (0.0, 0.0, 0.01, 0.02, 0.0))
    # xd = x + 2 p1 x y + p2 (r2 + 2 x^2) = 0.1 + 0.0004 + 0.0014; yd = y + p1 (r2 + 2 y^2) + 2 p2 x y = 0.2 + 0.0013 + 0.0008
    np.testing.assert_allclose(tangential.project(np.array([[0.1, 0.2, 1.0]])), [[60.18, 60.21]], atol=1e-9)
    # pixel rays invert the distortion: project(ray) returns the pixel center
    rays = camera.pixel_rays()
    np.testing.assert_allclose(camera.project(rays[[3, 70], [5, 90]]), [[5.5, 3.5], [90.5, 70.5]], atol=1e-6)


def test_extrinsic_from_quaternion_round_trips():
    rng = np.random.default_rng(0)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    q *= np.sign(q[3])
    np.testing.assert_allclose(matrix_to_quaternion(quaternion_to_matrix(q)), q, atol=1e-12)


def test_nearest_lookup_reads_the_covering_map_pixel():
    values = np.arange(2 * 40 * 50, dtype=np.float32).reshape(2, 40, 50)  # half the image's resolution
    pixel = np.array([[59.9, 61.0], [99.99, 79.99], [0.0, 0.0]])
    out = sample_map(values, pixel, (100, 80), "nearest")
    expected = np.stack([values[:, 30, 29], values[:, 39, 49], values[:, 0, 0]])
    np.testing.assert_array_equal(out, expected)
    labels = np.arange(80 * 100).reshape(80, 100)
    assert sample_map(labels, pixel, (100, 80)).tolist() == [61 * 100 + 59, 79 * 100 + 99, 0]


def test_bilinear_lookup_equals_torch_upsampling_then_truncation():
    rng = np.random.default_rng(1)
    values = rng.uniform(1, 50, (3, 20, 30)).astype(np.float32)
    full = torch.nn.functional.interpolate(torch.from_numpy(values)[None], size=(80, 100), mode="bilinear", align_corners=False)[0].numpy()
    pixel = rng.uniform(0, [100, 80], (500, 2))
    pixel[:4] = [[0, 0], [99.5, 79.5], [0.2, 79.9], [50.0, 40.0]]
    out = sample_map(values, pixel, (100, 80), "bilinear")
    expected = full[:, np.floor(pixel[:, 1]).astype(int), np.floor(pixel[:, 0]).astype(int)].T
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-4)


def test_zbuffer_drops_points_hidden_behind_nearer_ones():
    points = np.array([[0.1, 0.1, 2.0], [0.25, 0.25, 5.0], [0.1, 0.1, 2.3], [-0.2, 0.0, 4.0]])  # 2nd hides behind 1st
    visible = project_scan(points, CAMERA, np.eye(4), ProjectionConfig(zbuffer=True, zbuffer_cell_px=4, zbuffer_tolerance_m=0.5))
    assert visible.index.tolist() == [0, 2, 3]
    assert project_scan(points, CAMERA, np.eye(4)).index.tolist() == [0, 1, 2, 3]


def test_nan_points_are_an_error():
    with pytest.raises(ValueError, match="NaN or inf.*row 1"):
        project_scan(np.array([[0, 0, 1.0], [np.nan, 0, 1]]), CAMERA, np.eye(4))


def test_frames_are_binned_in_order_with_a_short_last_bin():
    frames = [ProjectedFrame(i, np.full((i + 1, 3), i, float), np.full(i + 1, i), np.array([i, i, i]), np.arange(i + 1), np.zeros((i + 1, 2)))
              for i in range(5)]
    bins = list(bin_frames(iter(frames), 2))
    assert [b.frames for b in bins] == [[0, 1], [2, 3], [4]]
    assert isinstance(bins[0], Bin) and bins[0].values.tolist() == [0, 1, 1]
    assert bins[1].sensor_origin.tolist() == [3, 3, 3]


def test_real_rellis3d_frame_projects_onto_agreeing_labels():
    """RELLIS-3D's own example frame: its points must land on label-image pixels of their own class.
    Measured: 7,616 of 131,072 points in the image; 76.7 % agree on raw ids, 79.6 % after the v3 remap
    (disagreements sit on object edges, the person and thin branches, where the LiDAR and camera see
    past each other)."""
    seq = Rellis3DSequence(shared_path("data", "rellis_example"))
    frame = seq.frames[0]
    assert frame.index == 104 and frame.label_image is not None and not frame.label_is_color
    projected = project_scan(seq.read_scan(frame), seq.camera, seq.lidar_to_camera)
    assert len(projected.index) == 7616
    pixel_ids = sample_map(seq.read_label_ids(frame), projected.pixel, (seq.camera.width, seq.camera.height))
    point_ids = seq.read_point_labels(frame)[projected.index]
    table = original_to_v3_table()
    raw_agreement = (pixel_ids == point_ids).mean()
    v3_agreement = (table[pixel_ids] == table[point_ids]).mean()
    assert raw_agreement == pytest.approx(0.767, abs=0.005)
    assert v3_agreement == pytest.approx(0.796, abs=0.005)
    zbuffered = project_scan(seq.read_scan(frame), seq.camera, seq.lidar_to_camera, ProjectionConfig(zbuffer=True))
    assert len(zbuffered.index) < len(projected.index)
