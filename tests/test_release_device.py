"""The release mode's preprocessing after its cut, built by the parallel kernels (``methods.release_device``),
gives the host path's map bit for bit, on Warp's CPU backend (and on CUDA where Warp sees a GPU): its
parts against the host's, and whole maps of bench scans through the Mapper."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from conftest import REPO, shared_path

from evsemmap_warp.config import load_config
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.methods import release_compat as er
from evsemmap_warp.methods import release_device, sbki_compat

PRESET = REPO / "configs/presets/release.yaml"


@pytest.mark.parametrize("cap", [1, 3, 11])
def test_the_capped_points_are_the_host_paths(device, cap):
    rng = np.random.default_rng(cap)
    points = rng.uniform(-3, 5, (20_000, 3)).astype(np.float32)
    points[:40] = np.round(points[:40] / np.float32(0.4)) * np.float32(0.4)  # on block faces and ds lines
    points[40:80] = points[80]  # many copies: more than the cap in one block
    block_size = sbki_compat.block_size_m(0.2, 2)
    host = np.flatnonzero(er.first_per_block(er.snapped_block_keys(points, 0.5, block_size), cap))
    lo, hi = points.min(axis=0), points.max(axis=0)
    kept = release_device.capped_points_on_device(wp.array(points, dtype=wp.vec3, device=device), lo, hi, 0.5, block_size, cap)
    np.testing.assert_array_equal(kept.numpy(), host)
    one = release_device.capped_points_on_device(wp.array(points[:1], dtype=wp.vec3, device=device), points[0], points[0], 0.5, block_size, cap)
    np.testing.assert_array_equal(one.numpy(), [0])


@pytest.mark.parametrize("method, workers, scans", [("ebs", 1, 3), ("dempster", 2, 11)])
def test_a_map_from_the_device_preprocessing_is_the_host_paths_bit_for_bit(device, method, workers, scans):
    # 11 scans on 2 workers prepared ahead hold several scratch sets at once and reuse them.
    data = np.load(shared_path("data", "bench", "rellis_like_30scans.npz"))
    from evsemmap_warp.data.datasets import open_dataset

    run = load_config([PRESET, REPO / "configs/datasets/bench_rellis_like.yaml"], method=method)
    scans = [scan for _, scan in zip(range(scans), open_dataset(run.dataset))]
    assert len(data["scan_offsets"]) > 3
    maps = []
    for on_device in (False, True):
        mapper = Mapper(run.mapping, 9, workers=workers, device=device)
        mapper.integrator.preprocess_on_device = on_device
        kept = [stats.kept_points for stats in mapper.integrate_many(scans)]
        maps.append((kept, mapper.voxels()[0]))
    (host_kept, host_map), (device_kept, device_map) = maps
    assert device_kept == host_kept and len(host_map.index) > 10_000
    np.testing.assert_array_equal(device_map.index, host_map.index)
    np.testing.assert_array_equal(device_map.rows(), host_map.rows())


def test_a_scan_that_outgrows_its_reserved_room_is_redone_to_the_same_map(device, monkeypatch):
    # Room for 16 (point, block) pairs: the first scan outgrows it, gathers nothing, is built again with room
    # for what it counted and gathered; the map is the host path's, and a later scan reads once.
    from test_host_reads import assert_outgrown_room_is_redone_to_the_host_map

    from evsemmap_warp.data.datasets import open_dataset
    from evsemmap_warp.methods import sbki_device

    shared_path("data", "bench", "rellis_like_30scans.npz")  # the bench config's workload, or a skip that says why
    run = load_config([PRESET, REPO / "configs/datasets/bench_rellis_like.yaml"], method="ebs")
    scans = [scan for _, scan in zip(range(2), open_dataset(run.dataset))]
    monkeypatch.setattr(sbki_device, "PAIRS_GUESS_PER_POINT", 0.0)
    assert_outgrown_room_is_redone_to_the_host_map(run.mapping, scans, device)
