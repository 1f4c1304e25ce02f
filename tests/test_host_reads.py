"""What ``Mapper.integrate`` asks of the device per scan once warm, counted on the CPU backend: reads
back to the host, new device allocations, and host arrays handed to kernels, for the clean-mode methods.

A read is what waits for the device and copies to the host on a GPU (``wp.array.numpy``, ``.list``, a
``wp.copy`` into a CPU array); an allocation is a call to Warp's allocator or a ``wp.HashGrid``; a
host array is a ``wp.array`` made over host data (free on the CPU; on a GPU the scan's inputs go
through the shard's reused, pinned staging buffers instead, ``core._staging``, tests/test_staging.py). The budget is per shard and scan: one read (the
launch's counters together), no allocation, and the scan's own inputs (points, lengths, uncertainty,
payload). A scan that finds the table full reads its failure flags too and relaunches; the scans
counted here (the same scan again, the map warm) never do.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import pytest
from conftest import REPO

from evsemmap_warp.config import load_config
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.core.warp_runtime import init_warp

wp = init_warp()

PRESET = REPO / "configs/presets/rellis3d.yaml"
# Per shard and scan, warm: reads, allocations, host arrays (points, lengths, uncertainty, payload).
# Each launch allocating its failure flags and update count, and reading the key count around it, made
# 6 reads, 2 allocations and 5 host arrays per shard and scan.
BUDGET = {"reads": 1, "allocations": 0, "host_arrays": 4}
# Methods that stage a fifth input: ConvBKI its stencil weights, SEE-CSOM its points' owner blocks and
# target lengths (instead of lengths).
FIVE_INPUTS = {"convbki", "see-csom"}


def budget_of(method: str) -> dict:
    """The per-shard budget of a warm scan of ``method``."""
    return dict(BUDGET, host_arrays=BUDGET["host_arrays"] + (method in FIVE_INPUTS))


@dataclass
class Counts:
    reads: int = 0
    allocations: int = 0
    host_arrays: int = 0


@contextmanager
def counting():
    """Count reads, allocations and host arrays (see the module's description) while the block runs, in
    every thread (a shard's lane runs its launches)."""
    from warp._src import context as wp_context

    counts = Counts()
    lock = threading.Lock()
    inside = threading.local()  # a read made by another counted read (numpy() inside list()) counts once

    def tally(field):
        with lock:
            setattr(counts, field, getattr(counts, field) + 1)

    def reading(method):
        def wrapped(self, *args, **kwargs):
            if getattr(inside, "depth", 0) == 0:
                tally("reads")
            inside.depth = getattr(inside, "depth", 0) + 1
            try:
                return method(self, *args, **kwargs)
            finally:
                inside.depth -= 1

        return wrapped

    originals = []

    def patch(owner, name, value):
        originals.append((owner, name, getattr(owner, name)))
        setattr(owner, name, value)

    patch(wp.array, "numpy", reading(wp.array.numpy))
    patch(wp.array, "list", reading(wp.array.list))
    original_copy = wp.copy

    def copy(dest, src, *args, **kwargs):
        if dest.device.is_cpu and getattr(inside, "depth", 0) == 0:
            tally("reads")
        return original_copy(dest, src, *args, **kwargs)

    patch(wp, "copy", copy)
    for allocator in (wp_context.CpuDefaultAllocator, wp_context.CpuPinnedAllocator):
        original_allocate = allocator.allocate

        def allocate(self, size, original_allocate=original_allocate):
            tally("allocations")
            return original_allocate(self, size)

        patch(allocator, "allocate", allocate)
    original_grid = wp.HashGrid.__init__

    def grid_init(self, *args, **kwargs):
        tally("allocations")
        original_grid(self, *args, **kwargs)

    patch(wp.HashGrid, "__init__", grid_init)
    original_array = wp.array.__init__

    def array_init(self, data=None, *args, **kwargs):
        if data is not None and getattr(inside, "depth", 0) == 0:
            tally("host_arrays")
        original_array(self, data, *args, **kwargs)

    patch(wp.array, "__init__", array_init)
    try:
        yield counts
    finally:
        for owner, name, value in reversed(originals):
            setattr(owner, name, value)


def _scan(seed: int = 0, n: int = 12_000, k: int = 9):
    """A LiDAR-like scan: rings of points on a ground plane 1.2 m below the sensor, walls beyond 12 m."""
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(0, 2 * np.pi, n)
    elevation = np.deg2rad(rng.uniform(-22.5, -1.0, n))
    reach = np.minimum(1.2 / np.tan(-elevation), 12 + rng.uniform(0, 2, n))
    points = np.column_stack([reach * np.cos(azimuth), reach * np.sin(azimuth), -np.minimum(reach * np.tan(-elevation), 1.2)])
    alpha = np.ones((n, k))
    alpha[np.arange(n), rng.integers(1, k, n)] += rng.gamma(2.0, 200.0, n)  # confident: EBS's adaptive lengths reach voxels
    return points, alpha


def per_scan_counts(method: str, workers: int, warm_scans: int = 3, counted_scans: int = 3) -> list[Counts]:
    """Counts of each of ``counted_scans`` scans after ``warm_scans`` of the same scan (the map warm: no new
    voxel, so no growth)."""
    points, alpha = _scan()
    origin = np.zeros(3)  # the sensor's place in _scan's frame (SEE-CSOM adds it as a free sample)
    mapper = Mapper(load_config([PRESET], method=method).mapping, alpha.shape[1], workers=workers)
    assert len(mapper.shards) == workers
    for _ in range(warm_scans):
        mapper.integrate(points, alpha, payload_type="alpha", sensor_origin=origin)
    out = []
    for _ in range(counted_scans):
        with counting() as counts:
            stats = mapper.integrate(points, alpha, payload_type="alpha", sensor_origin=origin)
        assert stats.voxel_updates > 0
        out.append(counts)
    return out


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("method", ["ebs", "s-csm", "s-bki", "dempster", "convbki"])
def test_a_warm_scan_reads_once_per_shard_and_allocates_nothing(method, workers):
    counted = per_scan_counts(method, workers)
    for counts in counted:
        for field, per_shard in budget_of(method).items():
            assert getattr(counts, field) <= per_shard * workers, (
                f"{method}, {workers} worker(s): {getattr(counts, field)} {field.replace('_', ' ')} in a warm scan, budget "
                f"{per_shard} per shard (all counts: {counts})")


@pytest.mark.parametrize("workers", [1, 2])
def test_see_csoms_launch_reads_once_per_shard_and_allocates_nothing(workers):
    # SEE-CSOM's preparation (training data, block statistics) is host work on any map: Warp's CPU kernels on
    # host arrays (device "cpu"), which this CPU-backend count cannot tell from the map's. What reaches the
    # map is its launch, held to the budget.
    points, alpha = _scan()
    origin = np.zeros(3)
    mapper = Mapper(load_config([PRESET], method="see-csom").mapping, alpha.shape[1], workers=workers)
    for _ in range(3):
        mapper.integrate(points, alpha, payload_type="alpha", sensor_origin=origin)
    for _ in range(3):
        prepared = mapper.prepare(points, alpha, payload_type="alpha", sensor_origin=origin)
        with counting() as counts:
            stats = mapper.launch(prepared)
        assert stats.voxel_updates > 0
        for field, per_shard in budget_of("see-csom").items():
            assert getattr(counts, field) <= per_shard * workers, f"see-csom, {workers} worker(s): {counts}"


# Reads per shard and warm scan of the radius kernel's deterministic strategies (``mapping.clean.
# scatter_strategy``): the sorted one reads its pair count and its distinct voxels' count, which size its
# next arrays, the hash-grid one its reached voxels' count (with the key set's failure flag), and both
# their launch's counters. They allocated 11 and 5 device arrays per scan (and the hash grid) and read 5.
STRATEGY_READS = {"sorted": 3, "gather": 2}


@pytest.mark.parametrize("strategy", ["sorted", "gather"])
@pytest.mark.parametrize("method", ["ebs", "s-bki"])
def test_the_deterministic_strategies_allocate_nothing_once_warm(method, strategy):
    from evsemmap_warp.config import CleanSettings, ScatterStrategy

    points, alpha = _scan()
    config = load_config([PRESET], method=method).mapping.replace(clean=CleanSettings(ScatterStrategy(strategy)))
    mapper = Mapper(config, alpha.shape[1], workers=1)
    for _ in range(3):
        mapper.integrate(points, alpha, payload_type="alpha")
    with counting() as counts:
        stats = mapper.integrate(points, alpha, payload_type="alpha")
    assert stats.voxel_updates > 0
    assert counts.allocations == 0 and counts.reads <= STRATEGY_READS[strategy], f"{method}, {strategy}: {counts}"


def test_the_counters_see_what_they_count():
    # Each kind of event, once, so that a Warp release renaming what is patched fails here, not silently.
    host = np.arange(4.0)
    with counting() as counts:
        a = wp.zeros(4, dtype=wp.float64, device="cpu")
        b = wp.array(host, dtype=wp.float64, device="cpu", copy=False)
        wp.copy(a, b)
        a.numpy()
        b.list()
        wp.HashGrid(4, 4, 4, device="cpu")
    assert counts == Counts(reads=3, allocations=2, host_arrays=1)


def test_a_scan_that_fills_the_table_still_maps_every_point():
    # A table too small for the scan: the launch runs out of room, reads its failure flags, grows and
    # relaunches the points that did not fit; the map is that of a table large enough from the start.
    points, alpha = _scan(1, n=3000)
    config = load_config([PRESET], method="s-bki").mapping
    small = Mapper(config, alpha.shape[1], workers=1, initial_capacity=16)
    large = Mapper(config, alpha.shape[1], workers=1, initial_capacity=1 << 20)
    for mapper in (small, large):
        mapper.integrate(points, alpha, payload_type="alpha")
        mapper.integrate(points + 0.37, alpha, payload_type="alpha")
    assert small.shards[0].grow_count > 0 and large.shards[0].grow_count == 0
    a, b = small.voxels().arrays, large.voxels().arrays
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.rows(), b.rows(), rtol=1e-12, atol=0)


def test_the_counters_kernel_matches_its_twin():
    from evsemmap_warp.kernels import hash_table as ht
    from evsemmap_warp.reference import hash_table as ht_ref

    key_count, updates, bricks = np.array([12345], np.int32), np.array([1 << 40], np.int64), np.array([(1 << 31) - 1], np.int32)
    for status in (np.zeros(0, np.int32), np.array([1, 70_000, -3, (1 << 31) - 1], np.int32)):
        out = wp.zeros(3 + len(status), dtype=wp.int64, device="cpu")
        wp.launch(ht.read_counters, dim=1, inputs=[wp.array(key_count, dtype=int, device="cpu"), wp.array(updates, dtype=wp.int64, device="cpu"),
                                                   wp.array(bricks, dtype=int, device="cpu"), wp.array(status, dtype=int, device="cpu"), out], device="cpu")
        np.testing.assert_array_equal(out.numpy(), ht_ref.read_counters(key_count, updates, bricks, status))


# Reads per warm scan of the like-for-like modes' device preprocessing, as counted on the CPU backend: the
# scan's status, read with the gather's counters. Each count that sized the next arrays was read back
# (7 reads per S-BKI scan of this workload, 4 per release scan); the stages now run over room the host
# knows, with their counts on the device (methods.device_scratch).
COMPAT_DEVICE_READS = {"sbki": 1, "release-ebs": 1}


@pytest.mark.parametrize("method", ["sbki", "release-ebs"])
def test_the_compat_modes_device_preprocessing_allocates_nothing_once_warm(method):
    # The like-for-like modes' preprocessing on the map's device (what a GPU map runs; forced here on the
    # CPU backend) keeps its arrays in a pool of scratch sets (methods.device_scratch), each held by one
    # scan until its launch is done: a warm scan allocates nothing, and reads no more than it does now.
    from conftest import shared_path

    from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings

    data = np.load(shared_path("data", "bench", "rellis_like_30scans.npz"))
    offsets = data["scan_offsets"]
    points = (data["xyz_mm"][offsets[0]:offsets[1]] / 1000.0).astype(np.float32)
    origin = data["origins_mm"][0] / 1000.0
    if method == "sbki":
        config = MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
                               compat=Compat.SBKI, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                               sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=4.0, max_range_m=None))
        payload, payload_type = data["label"][offsets[0]:offsets[1]].astype(np.int64), "label"
    else:
        config = load_config([REPO / "configs/presets/release.yaml"], method="ebs").mapping
        payload, payload_type = np.random.default_rng(0).gamma(2.0, 3.0, (len(points), 9)) + 1.0, "alpha"
    mapper = Mapper(config, 9, workers=1)
    mapper.integrator.preprocess_on_device = True
    for _ in range(2):
        mapper.integrate(points, payload, payload_type=payload_type, sensor_origin=origin)
    with counting() as counts:
        stats = mapper.integrate(points, payload, payload_type=payload_type, sensor_origin=origin)
    assert stats.voxel_updates > 0
    assert counts.allocations == 0, f"{method}: {counts}"
    assert counts.reads <= COMPAT_DEVICE_READS[method], f"{method}: {counts}"
    assert mapper.integrator._scratch.sets(mapper.device) == 1  # scan by scan, each scan gave its set back


def assert_outgrown_room_is_redone_to_the_host_map(mapping, scans, device) -> None:
    """Maps ``scans`` (two or more) with the compat mode's preprocessing on the host and on the device, where
    the caller made the device's first room too small (``methods.sbki_device``'s guesses): the first scan
    reads more than once (the status that says it ran out of room, then its redo's), the later ones once,
    and the kept counts and the map are the host path's."""
    maps = []
    for on_device in (False, True):
        mapper = Mapper(mapping, 9, workers=1, device=device)
        mapper.integrator.preprocess_on_device = on_device
        if on_device:
            with counting() as first:
                kept = [stats.kept_points for stats in mapper.integrate_many(scans[:1])]
            with counting() as later:
                kept += [stats.kept_points for stats in mapper.integrate_many(scans[1:])]
            assert first.reads > 1 and later.reads == len(scans) - 1, (first, later)
        else:
            kept = [stats.kept_points for stats in mapper.integrate_many(scans)]
        maps.append((kept, mapper.voxels()[0]))
    (host_kept, host_map), (device_kept, device_map) = maps
    assert device_kept == host_kept
    np.testing.assert_array_equal(device_map.index, host_map.index)
    np.testing.assert_array_equal(device_map.rows(), host_map.rows())
