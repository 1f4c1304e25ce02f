"""What lets a GPU map's host work overlap its kernels, checked on the CPU backend. Scan inputs reach the
device through buffers a shard keeps (``core._staging``): on the CPU numpy's memory is read in place;
the GPU's path (device buffers reused from scan to scan, grown by half again when outgrown) runs on the
CPU with ``reuse_on_cpu``, and a map made through it is the map made without it, bit for bit. A GPU map
prepares the next scans on a thread while this one launches (``Mapper.prepare_ahead``): the same map."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from conftest import REPO

from evsemmap_warp.config import load_config
from evsemmap_warp.core._staging import Staging
from evsemmap_warp.core.mapper import Mapper


def test_the_cpu_reads_numpys_memory_in_place():
    values = np.arange(12.0).reshape(4, 3)
    uploaded = Staging("cpu").upload("points", values, wp.vec3d, np.float64)
    assert uploaded.ptr == values.ctypes.data
    np.testing.assert_array_equal(uploaded.numpy(), values)


def test_reused_buffers_hold_each_scans_values_and_grow_when_outgrown():
    staging = Staging("cpu", reuse_on_cpu=True)
    first = staging.upload("points", np.ones((100, 3)), wp.vec3d, np.float64)
    second = staging.upload("points", np.full((80, 3), 2.0), wp.vec3d, np.float64)
    assert second.ptr == first.ptr and second.shape == (80,)  # the same buffer, this scan's length
    np.testing.assert_array_equal(second.numpy(), np.full((80, 3), 2.0))
    grown = staging.upload("points", np.arange(303.0).reshape(101, 3), wp.vec3d, np.float64)
    assert grown.ptr != first.ptr and grown.shape == (101,)
    np.testing.assert_array_equal(grown.numpy(), np.arange(303.0).reshape(101, 3))
    labels = staging.upload("labels", np.array([3, 1, 2]), wp.int32, np.int32)  # its own buffer, converted
    np.testing.assert_array_equal(labels.numpy(), [3, 1, 2])
    assert staging.upload("labels", np.zeros(0), wp.int32, np.int32).shape == (0,)


@pytest.mark.parametrize("method", ["ebs", "s-bki", "convbki", "see-csom"])
def test_a_map_made_through_reused_buffers_is_the_same(method):
    rng = np.random.default_rng(4)
    config = load_config([REPO / "configs/presets/rellis3d.yaml"], method=method).mapping
    scans = [(rng.uniform(-6, 6, (n, 3)), rng.gamma(2.0, 2.0, (n, 5)) + 1.0) for n in (3000, 2000, 4000)]
    maps = []
    for reuse in (False, True):
        mapper = Mapper(config, 5, workers=1)
        for shard in mapper.shards:
            shard.staging = Staging("cpu", reuse_on_cpu=reuse)
        for points, alpha in scans:
            mapper.integrate(points, alpha, payload_type="alpha", sensor_origin=np.zeros(3))
        maps.append(mapper.voxels()[0])
    assert len(maps[0].index) > 100
    np.testing.assert_array_equal(maps[1].index, maps[0].index)
    np.testing.assert_array_equal(maps[1].rows(), maps[0].rows())


@pytest.mark.parametrize("preset, method, on_device", [("rellis3d", "ebs", False), ("release", "dempster", True)])
def test_preparing_ahead_with_one_worker_gives_the_same_map(preset, method, on_device):
    # What a GPU map does (Mapper.prepare_ahead): the next scans prepared on a thread while this one launches.
    from types import SimpleNamespace

    rng = np.random.default_rng(8)
    config = load_config([REPO / f"configs/presets/{preset}.yaml"], method=method).mapping
    scans = [SimpleNamespace(points=rng.uniform(-6, 6, (n, 3)), payload=rng.gamma(2.0, 2.0, (n, 9)) + 1.0, payload_type="alpha",
                             sensor_origin=np.zeros(3)) for n in (3000, 2000, 4000, 2500)]
    maps = []
    for ahead in (False, True):
        mapper = Mapper(config, 9, workers=1)
        mapper.prepare_ahead = ahead
        if hasattr(mapper.integrator, "preprocess_on_device"):
            mapper.integrator.preprocess_on_device = on_device
        stats = mapper.integrate_many(scans)
        maps.append(([s.voxel_updates for s in stats], mapper.voxels()[0]))
    (updates, first), (ahead_updates, ahead_map) = maps
    assert updates == ahead_updates and len(first.index) > 100
    np.testing.assert_array_equal(ahead_map.index, first.index)
    np.testing.assert_array_equal(ahead_map.rows(), first.rows())


def test_scratch_sets_keep_each_requests_buffer_and_the_pool_hands_out_free_sets():
    # The compat modes' device preprocessing keeps its arrays in scratch sets (methods.device_scratch).
    from evsemmap_warp.methods.device_scratch import ScratchPool

    pool = ScratchPool()

    def scan(scratch, n):  # one line asked twice per scan (as the VoxelGrid runs twice), one line once
        pair = [scratch.empty(n, wp.float64) for _ in range(2)]
        return pair + [scratch.full((n, 3), 7, wp.int32)]

    first = pool.take("cpu")
    arrays = scan(first, 100)
    assert len({a.ptr for a in arrays}) == 3 and arrays[2].numpy().tolist() == [[7, 7, 7]] * 100
    assert pool.take("cpu") is not first and pool.sets("cpu") == 2  # held: a second set
    first.release()
    again = pool.take("cpu")
    assert again is first
    smaller = scan(again, 60)
    assert [a.ptr for a in smaller] == [a.ptr for a in arrays] and smaller[0].shape == (60,)
    grown = scan(pool.take("cpu"), 60)  # the other set is still held: a third one
    assert pool.sets("cpu") == 3 and not {a.ptr for a in grown} & {a.ptr for a in arrays}
    again.release()
    bigger = scan(pool.take("cpu"), 1000)
    assert bigger[0].ptr != arrays[0].ptr and bigger[0].shape == (1000,) and bigger[2].numpy().shape == (1000, 3)
    assert scan(pool.take("cpu"), 0)[0].shape == (0,)


def test_a_scratch_set_taken_for_a_scan_that_fails_is_given_back():
    # A scan whose preparation raises never reaches its launch, which would have released its set.
    from evsemmap_warp.methods.device_scratch import ScratchPool

    pool = ScratchPool()
    with pytest.raises(ValueError):
        with pool.taken("cpu") as failed:
            raise ValueError("a bad scan")
    assert not failed.in_use
    with pool.taken("cpu") as held:
        pass
    assert held is failed and held.in_use  # a scan that prepared holds its set until its launch releases it


def test_scratch_uploads_go_through_kept_buffers_on_the_gpu_path():
    # On a GPU a scratch set's uploads are copied from a kept (pinned) host buffer into a kept device buffer;
    # the CPU backend takes that path here: the values arrive, and the next scan that takes the set reuses both.
    from evsemmap_warp.methods.device_scratch import ScratchPool

    pool = ScratchPool()

    def scan(values):  # the same line uploads in every scan, as the preprocessing's lines do
        scratch = pool.take("cpu")
        scratch.copies_uploads = True
        uploaded = scratch.upload(values, wp.vec3)
        np.testing.assert_array_equal(uploaded.numpy(), values)
        assert uploaded.ptr != values.ctypes.data  # a copy, not numpy's memory
        scratch.release()
        return uploaded.ptr, {key: buffer.ptr for key, buffer in scratch._pinned.items()}

    first = np.arange(12, dtype=np.float32).reshape(4, 3)
    assert scan(first) == scan(first[:3] * 2)


@pytest.mark.parametrize("values, dtype", [(np.arange(6, dtype=np.int64), wp.int32), (np.arange(12, dtype=np.float64).reshape(4, 3), wp.vec3)])
def test_scratch_uploads_of_another_numpy_type_arrive_as_values_on_the_gpu_path(values, dtype):
    # The pinned buffer must hold the values in the device array's layout: an int64 array uploaded as
    # int32 (or float64 rows as vec3) copied raw would arrive as other numbers on a GPU only.
    from evsemmap_warp.methods.device_scratch import ScratchPool

    scratch = ScratchPool().take("cpu")
    scratch.copies_uploads = True
    np.testing.assert_array_equal(scratch.upload(values, dtype).numpy(), values)
    scratch.release()


def test_a_gpu_maps_prepare_thread_and_its_launches_call_warp_in_turn(monkeypatch):
    # A GPU map prepares (on the device, in the compat modes) on a thread while the main thread launches;
    # both must hold core.warp_runtime.device_calls while they call Warp. Recorded here on the CPU backend.
    import threading
    from contextlib import contextmanager
    from types import SimpleNamespace

    from evsemmap_warp.core.integrators import gathers
    from evsemmap_warp.core import mapper as mapper_module

    turns = threading.RLock()
    callers = []

    @contextmanager
    def recorded(device):
        with turns:
            callers.append(threading.current_thread().name)
            yield

    monkeypatch.setattr(gathers, "device_calls", recorded)
    monkeypatch.setattr(mapper_module, "device_calls", recorded)
    rng = np.random.default_rng(9)
    config = load_config([REPO / "configs/presets/release.yaml"], method="ebs").mapping
    scans = [SimpleNamespace(points=rng.uniform(-6, 6, (n, 3)), payload=rng.gamma(2.0, 2.0, (n, 9)) + 1.0, payload_type="alpha",
                             sensor_origin=np.zeros(3)) for n in (3000, 2000, 4000)]
    mapper = Mapper(config, 9, workers=1)
    mapper.prepare_ahead = True
    mapper.integrator.preprocess_on_device = True
    mapper.integrate_many(scans)
    mapper.voxels()
    prepared = [name for name in callers if name.startswith("evsemmap-prepare")]
    assert len(prepared) == len(scans) and callers.count(threading.main_thread().name) == len(scans) + 1


def test_device_calls_lock_a_gpu_per_device_and_nothing_on_the_cpu():
    import contextlib

    from evsemmap_warp.core.warp_runtime import device_calls

    assert isinstance(device_calls("cpu"), contextlib.nullcontext)
    first = device_calls("cuda:0")
    assert device_calls("cuda:0") is first and device_calls("cuda:1") is not first
    with first, first:  # re-entrant: a launch that rebuilds its scan's inputs takes it again
        pass
