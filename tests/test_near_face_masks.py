"""The S-BKI gather's near-face masks (``kernels.block_gather.near_face_masks``): the kernel against its
numpy twin on random blocks with the edge cases (no points, one point, points on cell and block faces,
blocks that start and end inside a word and across words, far coordinates, more room than points), every
point the gather's box test keeps held by its mask, and maps that do not depend on the masks."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.kernels import block_gather
from evsemmap_warp.methods import sbki_compat, sbki_device
from evsemmap_warp.reference import block_gather as twin

RESOLUTION, LENGTH, CELLS = 0.2, 0.3, 2
BLOCK = float(sbki_compat.block_size_m(RESOLUTION, 2))


def _blocks_and_points(rng, blocks: int, corner: int, most_points: int):
    """Distinct blocks near ``corner`` (in blocks) with 1..most_points points each inside their closed
    float32 box, some on its faces and on cell faces: (blocks [B, 3], point_start [B + 1], scaled points)."""
    keys = rng.choice(27 * blocks, size=blocks, replace=False)
    index = np.stack([keys // (9 * blocks), (keys // 3) % (3 * blocks), keys % 3], axis=1).astype(np.int64) + corner
    counts = rng.integers(1, most_points + 1, blocks)
    owner = np.repeat(np.arange(blocks), counts)
    half = np.float32(BLOCK / 2)
    center = (index[owner] * np.float64(BLOCK)).astype(np.float32)
    points = center + rng.uniform(-half, half, (len(owner), 3)).astype(np.float32)
    on_face = rng.random((len(owner), 3)) < 0.1
    points[on_face] = (center + np.sign(rng.normal(size=(len(owner), 3))).astype(np.float32) * half)[on_face]
    on_cell_face = rng.random((len(owner), 3)) < 0.05
    points[on_cell_face] = center[on_cell_face]
    return index, np.r_[0, np.cumsum(counts)].astype(np.int32), points / np.float32(LENGTH)


def _masks_on(device, blocks, point_start, scaled, room: int = 0):
    pairs = len(scaled)
    padded = np.r_[scaled, np.full((room, 3), 1e6, np.float32)].astype(np.float32)  # garbage past the count
    return sbki_device.near_face_masks(
        wp.array(padded, dtype=wp.vec3, device=device), wp.array([pairs], dtype=int, device=device),
        wp.array(np.r_[point_start, np.full(room, pairs)].astype(np.int32), dtype=int, device=device),
        wp.array(np.r_[blocks, np.zeros((room, 3), np.int64)].astype(np.int32), dtype=wp.vec3i, device=device),
        wp.array([len(blocks)], dtype=int, device=device), cells_per_block=CELLS, resolution_m=RESOLUTION, grid_offset_m=0.0,
        length_m=LENGTH).numpy()


def test_the_masks_faces_are_the_sources_order():
    # The kernel boxes face f's test block as the point's block less FACE_OFFSETS[f]; the gather reads
    # face f's mask for source f + 1, which the tables list in EXTENDED_BLOCK_OFFSETS order.
    np.testing.assert_array_equal(twin.FACE_OFFSETS, sbki_compat.EXTENDED_BLOCK_OFFSETS[1:])
    assert block_gather.FACE_COUNT == len(twin.FACE_OFFSETS) == block_gather.EXTENDED_BLOCK_COUNT - 1


@pytest.mark.parametrize("blocks, corner, most_points, room", [
    (1, 0, 1, 0),          # one point
    (3, -2, 40, 70),       # blocks inside one word; words of room past the count
    (60, 5, 150, 3),       # blocks across words, several words per block
    (40, 75_000, 90, 0),   # 30 km out: float32 coordinates with few bits below the cell
])
def test_near_face_masks_match_their_twin(device, blocks, corner, most_points, room):
    rng = np.random.default_rng(blocks * 7 + most_points)
    index, point_start, scaled = _blocks_and_points(rng, blocks, corner, most_points)
    masks = _masks_on(device, index, point_start, scaled, room)
    words = block_gather.near_face_words(len(scaled))
    want = twin.near_face_masks(scaled, point_start, index, cells_per_block=CELLS, resolution=RESOLUTION, grid_offset=0.0, length=LENGTH)
    np.testing.assert_array_equal(masks[:words], want)
    assert not masks[words:].any()


def test_no_points_no_masks(device):
    assert _masks_on(device, np.zeros((0, 3), np.int64), np.zeros(1, np.int32), np.zeros((0, 3), np.float32), room=5).shape == (1, 6)
    assert not _masks_on(device, np.zeros((0, 3), np.int64), np.zeros(1, np.int32), np.zeros((0, 3), np.float32), room=5).any()


def test_every_point_the_box_test_keeps_is_in_its_mask():
    # The gather visits a neighbour's points through its mask and then applies its own box test: the map
    # is the same as long as the mask holds every point that test keeps (float32, as the kernel boxes).
    rng = np.random.default_rng(5)
    index, point_start, scaled = _blocks_and_points(rng, 80, -40, 60)
    masks = twin.near_face_masks(scaled, point_start, index, cells_per_block=CELLS, resolution=RESOLUTION, grid_offset=0.0, length=LENGTH)
    owner = np.repeat(np.arange(len(index)), np.diff(point_start))
    kept = 0
    for f, offset in enumerate(twin.FACE_OFFSETS):
        first = (index[owner] - offset) * CELLS - CELLS // 2
        lo, hi = (((c.astype(np.float32) + np.float32(0.5)) * np.float32(RESOLUTION)) / np.float32(LENGTH) for c in (first, first + CELLS - 1))
        d = np.maximum(np.maximum(lo - scaled, scaled - hi), np.float32(0))
        keeps = (d * d).sum(axis=1, dtype=np.float32) < np.float32(block_gather.BOX_SKIP_DISTANCE2)
        q = np.flatnonzero(keeps)
        held = (masks[q // 64, f].view(np.uint64) >> (q % 64).astype(np.uint64)) & np.uint64(1)
        assert held.all()
        kept += len(q)
    held_bits = sum(bin(int(word)).count("1") for word in masks.view(np.uint64).reshape(-1))
    assert kept <= held_bits < 0.7 * 6 * len(scaled)  # and the masks spare the gather most far points


def _bench_like_config() -> MappingConfig:
    return MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
                         compat=Compat.SBKI, resolution_m=RESOLUTION, length_m=LENGTH, sigma0=10.0, prior=0.001,
                         sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=0.5))


@pytest.mark.parametrize("on_device", [False, True])
def test_the_map_does_not_depend_on_the_masks(monkeypatch, on_device):
    # Masks with every bit set make the gather test every neighbour's point again, as it did before
    # them: the map must be the same bit for bit, on the host path and on the device path.
    rng = np.random.default_rng(9)
    points = rng.uniform(0, 4, (4000, 3)).astype(np.float32)
    labels = rng.integers(0, 5, len(points))
    origin = np.array([2.0, 2.0, 3.0])

    def mapped():
        mapper = Mapper(_bench_like_config(), 5, origin=np.zeros(3), workers=1)
        mapper.integrator.preprocess_on_device = on_device
        mapper.integrate(points, labels, payload_type="label", sensor_origin=origin)
        return mapper.voxels()[0]

    computed = mapped()
    real = sbki_device.near_face_masks

    def every_bit(*args, **kwargs):
        masks = real(*args, **kwargs)
        masks.fill_(-1)
        return masks

    monkeypatch.setattr(sbki_device, "near_face_masks", every_bit)
    full = mapped()
    np.testing.assert_array_equal(computed.index, full.index)
    np.testing.assert_array_equal(computed.rows(), full.rows())
    assert computed.hits.sum() > 0
