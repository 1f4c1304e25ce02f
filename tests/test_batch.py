"""Batch mapping into map stores: the exported store is the map `evsemmap map` makes, for every method,
any chunk size, any worker count and either executor; stores are byte-identical whatever ran them;
killed workers and drivers change nothing; stores answer queries from the tiles they need; bad
configurations stop before any work."""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, stop_reading_partials_at
from evsemmap_warp.apps import batch
from evsemmap_warp.apps.batch import BatchOptions, planning, ray_executor, run_batch
from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.core.map_store import MapStore, StoreError
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.data.datasets import open_dataset
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

METHODS = ["s-csm", "s-bki", "ebs", "prob-adap-thr", "convbki", "see-csom", "dempster"]
TOY = REPO / "configs" / "datasets" / "sbki_toy.yaml"


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("batch") / "drive"
    generate_sequence(load_preset("tiny"), folder, progress=False)
    return folder


def _map(sources, method) -> Mapper:
    """What `evsemmap map` computes (same code path: datasets, Mapper with its default workers)."""
    run = load_config([str(s) for s in sources], method=method)
    dataset = open_dataset(run.dataset)
    mapper = Mapper(run.mapping, dataset.num_classes, class_names=dataset.class_names or None)
    for scan in dataset:
        mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
    return mapper


def _batch(sources, out, method="ebs", fault=None, **options) -> dict:
    options.setdefault("progress", False)
    return run_batch([str(s) for s in sources], BatchOptions(method=method, out=out, **options), log=lambda m: None, fault=fault)


def _assert_same_map(a: Mapper, b: Mapper, rtol=1e-12):
    (va, sa), (vb, sb) = a.voxels(), b.voxels()
    np.testing.assert_array_equal(va.index, vb.index)
    np.testing.assert_array_equal(sa.label, sb.label)
    np.testing.assert_array_equal(sa.state, sb.state)
    np.testing.assert_array_equal(va.hits, vb.hits)
    np.testing.assert_array_equal(va.touched, vb.touched)
    np.testing.assert_allclose(va.evidence, vb.evidence, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(va.weight_sum, vb.weight_sum, rtol=rtol, atol=1e-12)
    assert a.scans_integrated == b.scans_integrated and a.points_integrated == b.points_integrated


def _pool_context(drive, store: Path):
    """The Context a pool's workers receive for mapping ``drive`` with EBS into ``store``."""
    _, sources, config, _, _ = batch.plan_batch([str(drive)], BatchOptions(method="ebs", out=store))
    origin_index, class_names, *_ = batch.probe(sources, config)
    return batch.Context(store, sources, config, sources[0].num_classes, class_names, origin_index, 256)


def _files(store: Path) -> dict[str, bytes]:
    return {str(p.relative_to(store)): p.read_bytes() for p in sorted(store.rglob("*")) if p.is_file() and not p.name.startswith(".fault")}


def _assert_same_bytes(a: Path, b: Path):
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    different = [name for name in fa if fa[name] != fb[name]]
    assert not different, different


@pytest.mark.parametrize("method", METHODS)
def test_the_exported_store_is_the_map_for_every_method(drive, tmp_path, method):
    summary = _batch([drive], tmp_path / "store", method, executor="inline", chunk_frames=2)
    assert summary["chunks"] == 3 and summary["tiles"] > 1
    store = MapStore(tmp_path / "store")
    _assert_same_map(_map([drive], method), store.to_mapper())
    assert store.voxel_count == summary["voxels"]


@pytest.mark.parametrize("method", ["s-bki", "s-csm"])
def test_the_sbki_compatibility_mode_batches_exactly(tmp_path, method):
    _batch([TOY], tmp_path / "store", method, executor="inline", chunk_frames=5, tile_voxels=64)
    _assert_same_map(_map([TOY], method), MapStore(tmp_path / "store").to_mapper())


def test_any_chunk_size_and_any_worker_count_give_the_map_and_one_store(drive, tmp_path):
    reference = _map([drive], "ebs")
    for chunk in (1, 4):
        _batch([drive], tmp_path / f"inline{chunk}", executor="inline", chunk_frames=chunk)
        _assert_same_map(reference, MapStore(tmp_path / f"inline{chunk}").to_mapper())
    _batch([drive], tmp_path / "two", executor="local", workers=2, chunk_frames=1)
    _batch([drive], tmp_path / "one", executor="local", workers=1, chunk_frames=1)
    _assert_same_bytes(tmp_path / "inline1", tmp_path / "two")
    _assert_same_bytes(tmp_path / "inline1", tmp_path / "one")


def test_the_fold_width_is_asked_or_one_lane_per_six_workers_on_the_nodes_with_ray_past_one():
    from evsemmap_warp.apps.batch.planning import fold_width, folds_on_nodes

    assert fold_width(None) == 1 and fold_width(3) == 3 and fold_width(3, workers=64) == 3
    assert [fold_width(None, workers) for workers in (1, 6, 7, 12, 13, 32)] == [1, 1, 2, 2, 3, 6]
    pool, ray = BatchOptions(method="ebs", out="s", executor="local"), BatchOptions(method="ebs", out="s", executor="ray")
    assert not folds_on_nodes(pool, 32) and not folds_on_nodes(ray, 6) and folds_on_nodes(ray, 7)
    assert folds_on_nodes(BatchOptions(method="ebs", out="s", executor="ray", fold_workers=1), 2)
    for wrong in (0, -1, 1.5, True):  # the Python API's BatchOptions(fold_workers=...): the command line's flag is checked
        with pytest.raises(ConfigError, match=rf"fold_workers = {wrong!r}: give a whole number of fold lanes"):
            fold_width(wrong)


def test_tiles_folded_side_by_side_give_the_serial_folds_store(drive, tmp_path, monkeypatch):
    """Each tile's partials are folded in chunk order whatever the fold width, so the bits are the serial fold's:
    with room for one tile in the lanes, tiles leave, are written and come back at every turn of the drive,
    and while several lanes fold (and encode) different tiles at once."""
    from evsemmap_warp.apps.batch import reduction

    _batch([drive], tmp_path / "serial", executor="inline", chunk_frames=1, fold_workers=1)
    monkeypatch.setattr(reduction, "FOLD_CACHE_TILES", 1)
    for width in (2, 3, 5):
        summary = _batch([drive], tmp_path / f"x{width}", executor="local", workers=2, chunk_frames=1, fold_workers=width)
        assert summary["fold_lanes"]["width"] == width and summary["fold_lanes"]["lane_seconds"] > 0
        assert summary["tile_writes"] > summary["tiles"]  # tiles were written before the end and folded into again
        _assert_same_bytes(tmp_path / "serial", tmp_path / f"x{width}")


def test_a_failed_fold_stops_the_run_at_the_next_chunk_not_at_the_end(drive, tmp_path, monkeypatch):
    """A tile the drive keeps passing stays in the lanes until the end: its failed fold is raised at the driver's
    next hand-out, not when the tile is written (TileFolder.finish never runs)."""
    from evsemmap_warp.apps.batch import reduction
    from evsemmap_warp.core import map_store

    original, finishing = map_store.read_partial, []

    def bad_chunk_1(path, columns, tile_voxels, identity, chunk):
        if chunk == 1:
            raise map_store.StoreError(f"{path}: a bad partial")
        return original(path, columns, tile_voxels, identity, chunk)

    monkeypatch.setattr(map_store, "read_partial", bad_chunk_1)
    monkeypatch.setattr(reduction.TileFolder, "finish", lambda self: finishing.append(self))
    with pytest.raises(map_store.StoreError, match="a bad partial"):
        _batch([drive], tmp_path / "store", executor="inline", chunk_frames=1)
    assert not finishing


def test_a_run_failing_in_a_fold_lane_resumes_to_the_same_store(drive, tmp_path, monkeypatch):
    """A fold that fails (here: chunk 3's partials) stops the run; the tiles written meanwhile by other lanes hold
    only chunks folded in order before them, so the rerun folds exactly what each tile lacks."""
    from evsemmap_warp.apps.batch import reduction
    from evsemmap_warp.apps.batch.store import chunk_dir
    from evsemmap_warp.core import map_store, tile_codec

    _batch([drive], tmp_path / "clean", executor="inline", chunk_frames=1)
    monkeypatch.setattr(reduction, "FOLD_CACHE_TILES", 1)
    original = stop_reading_partials_at(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        _batch([drive], tmp_path / "killed", executor="inline", chunk_frames=1, fold_workers=3)
    third = chunk_dir(tmp_path / "killed", 3)
    for tile in (tmp_path / "killed" / "tiles").glob("*.vox"):  # a tile that says it holds chunk 3 does
        if tile_codec.read_voxel_header(tile)["folded_through"] >= 3:
            assert not (third / f"{tile.stem}{map_store.PARTIAL_SUFFIX}").exists(), tile
    assert list(third.glob(f"*{map_store.PARTIAL_SUFFIX}"))  # chunk 3's partials wait for the rerun
    monkeypatch.setattr(map_store, "read_partial", original)
    assert _batch([drive], tmp_path / "killed", executor="inline", chunk_frames=1, fold_workers=2)["chunks_resumed"] >= 4
    _assert_same_bytes(tmp_path / "clean", tmp_path / "killed")


def test_ray_folds_tiles_in_lanes_on_the_nodes_to_the_serial_folds_store(drive, tmp_path, monkeypatch):
    """On Ray, each tile is folded by one lane (an actor) in chunk order: tiles leaving the lanes and coming back,
    three lanes folding at once, give the serial fold's bytes."""
    pytest.importorskip("ray")
    from evsemmap_warp.apps.batch import reduction

    _batch([drive], tmp_path / "serial", executor="inline", chunk_frames=1, fold_workers=1)
    monkeypatch.setattr(reduction, "FOLD_CACHE_TILES", 1)
    summary = _batch([drive], tmp_path / "ray", executor="ray", workers=2, chunk_frames=1, fold_workers=3)
    assert summary["fold_lanes"]["width"] == 3 and summary["fold_lanes"]["lane_seconds"] > 0
    assert summary["tile_writes"] > summary["tiles"] and summary["fold_lanes"]["restarts"] == 0
    shutil.rmtree(ray_executor.node_scratch(tmp_path / "ray"), ignore_errors=True)
    _assert_same_bytes(tmp_path / "serial", tmp_path / "ray")


def test_lost_ray_fold_lanes_are_rebuilt_from_the_partials_to_the_same_store(drive, tmp_path, monkeypatch):
    """The lanes (actors) killed mid-run, as their node's loss kills them, one at least with a tile in its memory
    (the lanes keep one: some tiles written and folded into again, others waiting for their write): a new lane gets
    every partial its tiles absorbed since their last write, and the store is the serial fold's. Without the
    rebuild the run failed (the actor's death)."""
    ray = pytest.importorskip("ray")
    from evsemmap_warp.apps.batch import reduction

    _batch([drive], tmp_path / "serial", executor="inline", chunk_frames=1, fold_workers=1)
    monkeypatch.setattr(reduction, "FOLD_CACHE_TILES", 1)
    hand_out, killed = reduction.TileFolder.chunk_finished, []

    def kill_the_lanes_after_chunk_3(folder, number):
        hand_out(folder, number)
        if folder.frontier > 3 and not killed:
            killed.extend(folder.lanes.actors)
            for actor in killed:
                ray.kill(actor, no_restart=True)

    monkeypatch.setattr(reduction.TileFolder, "chunk_finished", kill_the_lanes_after_chunk_3)
    summary = _batch([drive], tmp_path / "ray", executor="ray", workers=2, chunk_frames=1, fold_workers=2)
    assert len(killed) == 2 and 1 <= summary["fold_lanes"]["restarts"] <= 2
    shutil.rmtree(ray_executor.node_scratch(tmp_path / "ray"), ignore_errors=True)
    _assert_same_bytes(tmp_path / "serial", tmp_path / "ray")


def test_a_bad_partial_in_a_ray_fold_lane_stops_the_run_with_its_evidence_kept(drive, tmp_path, monkeypatch):
    """A batch of folds that fails in a lane (chunk 2's partials, garbled on disk before the driver sends them) leaves
    the lane's tiles short of chunk 2: the lane refuses every later call, so no tile is encoded and written as if
    whole and the partials it lacks deleted. Without the refusal the run wrote them and deleted chunk 2's partials."""
    pytest.importorskip("ray")
    from evsemmap_warp.apps.batch import reduction
    from evsemmap_warp.apps.batch.store import chunk_dir
    from evsemmap_warp.core import map_store

    monkeypatch.setattr(reduction, "FOLD_CACHE_TILES", 1)
    hand_out, garbled = reduction.TileFolder.chunk_finished, []

    def garble_chunk_2(folder, number):
        if number == 2:
            garbled.extend(chunk_dir(folder.out, 2).glob(f"*{map_store.PARTIAL_SUFFIX}"))
            for path in garbled:
                path.write_bytes(b"not a partial")
        hand_out(folder, number)

    monkeypatch.setattr(reduction.TileFolder, "chunk_finished", garble_chunk_2)
    with pytest.raises(map_store.StoreError, match="chunk"):
        _batch([drive], tmp_path / "ray", executor="ray", workers=2, chunk_frames=1, fold_workers=2)
    assert garbled and all(path.exists() for path in garbled)
    shutil.rmtree(ray_executor.node_scratch(tmp_path / "ray"), ignore_errors=True)


def test_the_ray_executor_on_a_local_instance_it_starts_and_stops(drive, tmp_path):
    ray = pytest.importorskip("ray")
    _batch([drive], tmp_path / "inline", executor="inline", chunk_frames=2)
    # what a task of an earlier run into the store left in the scratch folder, under a process that runs on: no task
    # removes it (remove_dead_tasks_leftovers), the local instance's close does (its node is this machine)
    left = ray_executor.node_scratch(tmp_path / "ray") / "work" / f".chunk_000001.{batch.worker.process_tag()}.tmp"
    left.mkdir(parents=True)
    summary = _batch([drive], tmp_path / "ray", executor="ray", workers=2, chunk_frames=2)
    assert summary["executor"] == "ray" and summary["workers"] == 2
    assert not ray.is_initialized()  # the instance it started is gone
    _assert_same_bytes(tmp_path / "inline", tmp_path / "ray")
    assert not ray_executor.node_scratch(tmp_path / "ray").exists()  # where its tasks mapped, gone with them


def test_ray_workers_start_with_their_share_of_the_math_threads(monkeypatch):
    """Ray workers import numpy before a task runs: its BLAS pool must be sized when they start (a chunk ran
    about 20 % slower in a Ray worker than in the pool's, whose workers already started at their share)."""
    ray = pytest.importorskip("ray")
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")  # a user's own setting is kept
    executor = batch.RayExecutor(2, address=None)
    try:
        @ray.remote(num_cpus=1)
        def environment():
            import os

            return {name: os.environ.get(name) for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}

        seen = ray.get(environment.remote())
    finally:
        executor.close()
    share = str(max(1, (os.cpu_count() or 1) // 2))
    assert seen == {"OMP_NUM_THREADS": share, "OPENBLAS_NUM_THREADS": share, "MKL_NUM_THREADS": "3"}


def test_ray_is_stopped_when_the_run_it_was_started_for_fails_to_plan(tmp_path):
    """Ray starts while the run is planned: a plan that fails (bad input) must not leave it running."""
    ray = pytest.importorskip("ray")
    assert not ray.is_initialized()
    with pytest.raises((ConfigError, ValueError), match="nowhere"):
        _batch([tmp_path / "nowhere"], tmp_path / "store", executor="ray", workers=1)
    assert not ray.is_initialized()


@pytest.mark.parametrize("own_instance, most", [(True, 4), (False, 2)])
def test_ray_keeps_at_most_workers_tasks_running_on_an_instance_it_joins(own_instance, most):
    """--workers bounds what a run takes of a running Ray instance or cluster: two tasks per worker in flight
    ran a 1-worker run on both CPUs of a 2-CPU instance (bench_batch-20261203T222614Z: "1 worker" as fast as 2).
    A local instance the run starts has exactly ``workers`` CPUs, so there the next tasks may wait in Ray. And a
    finished task's successor is submitted before the driver folds its result (with one task per worker in
    flight a worker idled through every fold: running Ray with 1 worker 17 % behind the pool,
    bench_batch-20261203T230710Z)."""
    executor = object.__new__(batch.RayExecutor)
    in_flight, seen = [], []

    class FakeTask:
        @staticmethod
        def remote(fn, threads, context, submitted, sent, item):
            in_flight.append(item)
            return item

    class FakeRay:
        @staticmethod
        def wait(refs, num_returns, timeout=None):  # ray.wait
            seen.append(len(in_flight))
            in_flight.remove(refs[0])
            return [refs[0]], refs[1:]

        @staticmethod
        def get(ref):
            return ref * 10

    executor.ray, executor._task, executor.context_box = FakeRay, FakeTask, None
    executor.workers, executor.own_instance, executor.inputs = 2, own_instance, ray_executor.SAME_PATH
    executor._receive = FakeRay.get
    done, in_flight_while_folding = {}, []

    def fold(item, result):  # the driver's fold: a finished task's successor already runs meanwhile
        done[item[0]] = result
        in_flight_while_folding.append(len(in_flight))

    executor.run(None, [(i,) for i in range(9)], fold)
    assert done == {i: 10 * i for i in range(9)}
    assert max(seen) == most
    assert in_flight_while_folding[:9 - most] == [most] * (9 - most)


def test_a_ray_instance_that_cannot_be_joined_by_address_is_one_line_naming_the_address_and_the_token(monkeypatch):
    """Ray authenticates by token by default and joins by address only with RAY_AUTH_MODE=token set; without
    it the user saw a minute of Ray's retries and then "Failed to connect to Ray cluster"."""
    ray = pytest.importorskip("ray")
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)

    def refused(**options):
        raise ConnectionError("Failed to connect to Ray cluster at 10.0.0.9:6379")

    monkeypatch.setattr(ray, "init", refused)
    monkeypatch.setattr(ray_executor, "check_ray_address", lambda address, timeout_s: None)  # something answers there, but not to us
    with pytest.raises(ConfigError, match=r"--ray-address 10\.0\.0\.9:6379: could not join .*RAY_AUTH_MODE=token"):
        batch.RayExecutor(2, address="10.0.0.9:6379")
    monkeypatch.setenv("RAY_AUTH_MODE", "token")  # asked for already: no hint, the address and Ray's reason
    with pytest.raises(ConfigError, match=r"could not join the Ray instance \(Failed to connect .*\)$"):
        batch.RayExecutor(2, address="10.0.0.9:6379")


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_a_worker_killed_in_the_middle_of_a_chunk_changes_nothing(drive, tmp_path, executor):
    if executor == "ray":
        pytest.importorskip("ray")
    _batch([drive], tmp_path / "clean", executor="inline", chunk_frames=2)
    # the fault plan travels in the workers' Context (no environment variable): the pool's and Ray's workers
    _batch([drive], tmp_path / "killed", executor=executor, workers=2, chunk_frames=2, fault=batch.FaultPlan(kill_chunk=1))
    # the worker did die once (Ray's tasks map in their node's scratch folder, the pool's in the store)
    marked = (ray_executor.node_scratch(tmp_path / "killed") if executor == "ray" else tmp_path / "killed") / "work" / ".fault-1"
    assert marked.exists()
    if executor == "ray":
        shutil.rmtree(ray_executor.node_scratch(tmp_path / "killed"))
    assert not list((tmp_path / "killed" / "work").glob(".chunk_*"))  # and left nothing behind
    _assert_same_bytes(tmp_path / "clean", tmp_path / "killed")


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_a_stuck_worker_stops_the_run_in_one_line_and_the_rerun_resumes(drive, tmp_path, capsys, executor):
    if executor == "ray":
        pytest.importorskip("ray")
    started = time.monotonic()
    with pytest.raises(TimeoutError, match=r"no chunk finished in 4 s \(--chunk-timeout-s\): a worker or a node is stuck"):
        _batch([drive], tmp_path / "stuck", executor=executor, workers=1, chunk_frames=2, chunk_timeout_s=4,
               fault=batch.FaultPlan(kill_chunk=-1, hang_chunk=1))
    assert time.monotonic() - started < 60  # not the hour the stuck worker sleeps
    shutil.rmtree(ray_executor.node_scratch(tmp_path / "stuck"), ignore_errors=True)  # Ray's tasks keep the fault plan's folder
    _batch([drive], tmp_path / "stuck", executor="inline", chunk_frames=2)  # resumes: the same store as a clean run
    _batch([drive], tmp_path / "clean", executor="inline", chunk_frames=2)
    _assert_same_bytes(tmp_path / "clean", tmp_path / "stuck")


def test_a_failed_run_closes_its_pool_in_bounded_time_with_a_worker_stuck(drive, tmp_path):
    """A run that fails while a worker is stuck in its chunk (here: the tile callback raising on the first fold)
    ends in seconds, the stuck worker interrupted: the pool's own shutdown waited for its task without bound."""
    def fail(name, voxels):
        raise ValueError("the callback failed")

    failed = []

    def run():
        try:
            run_batch([str(drive)], BatchOptions(method="ebs", out=tmp_path / "store", workers=2, chunk_frames=2, progress=False),
                      log=lambda m: None, on_tile=fail, fault=batch.FaultPlan(kill_chunk=-1, hang_chunk=1))
        except ValueError as exc:
            failed.append(exc)

    runner = threading.Thread(target=run, daemon=True)  # a thread: without the fix the run never ends
    runner.start()
    runner.join(90)
    assert not runner.is_alive(), "the run did not end: closing the pool waited for the stuck worker"
    assert [str(exc) for exc in failed] == ["the callback failed"]


def test_the_fault_plan_is_a_test_seam_not_an_environment_variable():
    source = "".join(path.read_text() for path in Path(batch.__file__).parent.glob("*.py"))
    assert "EVSEMMAP_BATCH_FAULT" not in source and not hasattr(batch, "FAULT_VARIABLE")
    import pickle

    plan = batch.FaultPlan(kill_chunk=3)
    assert pickle.loads(pickle.dumps(plan)) == plan  # it reaches the pool's and Ray's workers in the Context


def test_the_automatic_chunk_size_depends_on_the_frames_only():
    assert BatchOptions(method="ebs", out=Path("x")).chunk_frames is None
    chosen, rule = batch.choose_chunk_frames(None, 89)  # the README's synth example
    assert chosen == 6 and rule.startswith("automatic: ceil(89 frames / 16)")
    assert -(-89 // chosen) >= 2 * 7  # two chunks per worker up to 7 workers
    assert batch.choose_chunk_frames(None, 5000)[0] == 100  # long drives: the former default
    assert batch.choose_chunk_frames(None, 3)[0] == 1
    assert batch.choose_chunk_frames(7, 89) == (7, "given: --chunk-frames")
    with pytest.raises(ConfigError, match="--chunk-frames 0"):
        batch.choose_chunk_frames(0, 89)


def test_short_inputs_give_every_worker_several_chunks_by_default(drive, tmp_path):
    auto = _batch([drive], tmp_path / "auto", executor="local", workers=2)
    frames = auto["frames"]
    assert auto["chunk_frames"] == -(-frames // 16) and auto["chunk_frames_rule"].startswith(f"automatic: ceil({frames} frames / 16)")
    assert auto["chunks"] >= 2 * auto["workers"]  # short inputs no longer run as one chunk on one worker
    assert json.loads((tmp_path / "auto" / "work" / "plan.json").read_text())["chunk_frames"] == auto["chunk_frames"]
    inline = _batch([drive], tmp_path / "inline", executor="inline")
    assert inline["chunk_frames"] == auto["chunk_frames"]  # not chosen from the worker count: the same store
    _assert_same_bytes(tmp_path / "auto", tmp_path / "inline")
    # the run's identity holds the number used: giving it explicitly resumes the same run
    again = _batch([drive], tmp_path / "auto", executor="inline", chunk_frames=auto["chunk_frames"])
    assert again["chunks_resumed"] == auto["chunks"] and again["chunk_frames_rule"] == "given: --chunk-frames"


def test_the_memory_check_suggests_a_chunk_size_that_fits(monkeypatch, tmp_path):
    per_voxel = batch.bytes_per_voxel(9)
    monkeypatch.setattr(planning, "available_memory", lambda: driver + 2 * (batch.WORKER_OVERHEAD_BYTES + 3000 * per_voxel))
    options = BatchOptions(method="ebs", out=tmp_path, chunk_frames=10)
    driver = planning.driver_bytes(options, 2)  # with the fold's tiles, in the driver with the pool's lanes
    assert driver == batch.DRIVER_OVERHEAD_BYTES + 2 * planning.FOLD_CACHE_TILES * planning.FOLD_TILE_BYTES
    ray = BatchOptions(method="ebs", out=tmp_path, executor="ray", fold_workers=3)  # a local instance: a process per lane
    assert planning.driver_bytes(ray, 8) == batch.DRIVER_OVERHEAD_BYTES + 3 * batch.WORKER_OVERHEAD_BYTES
    # 1000 voxels for the first scan, 500 new ones per scan after it: 5 scans fit in 3000 voxels a worker
    with pytest.raises(ConfigError, match=r"batch: --chunk-frames 10 with 2 workers needs .* use --chunk-frames 5 or fewer --workers"):
        batch.check_memory(options, 2, 10, 1000, 1500, 9)
    with pytest.raises(ConfigError, match=r"--chunk-frames 10 \(chosen automatically\) with 2 workers .* use --chunk-frames 5 or"):
        batch.check_memory(options, 2, 10, 1000, 1500, 9, automatic=True)
    assert batch.check_memory(options, 2, 5, 1000, 1500, 9)["chunk_voxels_estimate"] == 3000


def test_a_killed_driver_resumes_without_redoing_or_counting_twice(tmp_path):
    folder = tmp_path / "drive"
    generate_sequence(load_preset("tiny", trajectory__frames=20, trajectory__spacing_m=1.0), folder, progress=False)
    chunks = _batch([folder], tmp_path / "clean", executor="inline", chunk_frames=1)["chunks"]
    assert chunks >= 15
    out = tmp_path / "store"
    command = [sys.executable, "-m", "evsemmap_warp.apps.cli", "batch", str(folder), "--method", "ebs", "--out", str(out),
               "--workers", "1", "--chunk-frames", "1", "--fold-workers", "2", "--quiet"]
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and len(list((out / "work").glob("chunk_*"))) < 3:
        time.sleep(0.02)
    os.killpg(process.pid, signal.SIGKILL)  # the driver and its workers, as a reboot would
    process.wait()
    finished = {p.name: (p / "done.json").stat().st_mtime_ns for p in (out / "work").glob("chunk_*")}
    assert 3 <= len(finished) < chunks and not (out / "store.json").exists()
    done = subprocess.run(command[:-1], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"resuming: {len(finished)} of {chunks} chunks are mapped already" in done.stderr
    assert json.loads(done.stdout)["chunks_resumed"] == len(finished)
    redone = {name for name, mtime in finished.items() if (out / "work" / name / "done.json").stat().st_mtime_ns != mtime}
    assert not redone, redone
    _assert_same_bytes(tmp_path / "clean", out)


def test_queries_read_only_the_tiles_their_points_fall_in(drive, tmp_path):
    _batch([drive], tmp_path / "store", executor="inline", chunk_frames=3, tile_voxels=32)
    store = MapStore(tmp_path / "store")
    mapper = _map([drive], "ebs")
    voxels, _ = mapper.voxels()
    assert len(store.tiles) > 10
    some = mapper.voxel_centers(voxels.index[::997])
    name = sorted(store.tiles)[len(store.tiles) // 2]
    inside = mapper.voxel_centers(store.tile(name).voxels()[0].index[:50])
    fresh = MapStore(tmp_path / "store")
    result = fresh.query(inside)
    assert fresh.tiles_loaded == 1
    expected = mapper.query(inside)
    np.testing.assert_array_equal(result.label, expected.label)
    np.testing.assert_allclose(result.probabilities, expected.probabilities, rtol=1e-12)
    far = fresh.query(np.array([[1e6, 0, 0], [-5e5, 3e5, 10]]))
    assert (far.label == -1).all() and fresh.tiles_loaded == 1  # no tile there, none read
    everywhere = MapStore(tmp_path / "store").query(some)
    np.testing.assert_array_equal(everywhere.label, mapper.query(some).label)
    np.testing.assert_array_equal(everywhere.voxel_index, mapper.query(some).voxel_index)


def test_export_bounds_info_merge_and_view_of_stores(tmp_path, capsys):
    import yaml

    halves = []
    for name, first, last in (("a", 1, 6), ("b", 7, 12)):
        config = yaml.safe_load(TOY.read_text())
        config["dataset"].update(paths=[str(REPO / "tests/data/sbki_toy")], first_index=first, last_index=last)
        halves.append(tmp_path / f"{name}.yaml")
        halves[-1].write_text(yaml.safe_dump(config))
    for name, config in zip("ab", halves):
        assert main(["batch", str(config), "--method", "s-csm", "--out", str(tmp_path / name), "--workers", "1", "--quiet"]) == 0
    capsys.readouterr()
    full = _map([TOY], "s-csm")
    # two drives over one area: merged, as maps and as stores
    assert main(["merge", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "ab.npz")]) == 0
    _assert_same_map(full, Mapper.load(tmp_path / "ab.npz"))
    assert main(["export", str(tmp_path / "b"), "--out", str(tmp_path / "b.npz")]) == 0
    assert main(["merge", str(tmp_path / "a"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "ab_store"), "--tile-voxels", "64"]) == 0
    _assert_same_map(full, MapStore(tmp_path / "ab_store").to_mapper())
    capsys.readouterr()
    assert main(["info", str(tmp_path / "ab_store")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["voxels"] == full.voxel_count and info["tiles"] > 1 and info["method"] == "s-csm"
    # a box: exactly the map's voxels whose centers lie in it, from the tiles that meet it
    bounds = np.array([[-5.0, -5.0, -2.0], [5.0, 5.0, 2.0]])
    assert main(["export", str(tmp_path / "ab_store"), "--bounds", *map(str, bounds.ravel()), "--out", str(tmp_path / "box.npz")]) == 0
    report = json.loads(capsys.readouterr().out)
    box = Mapper.load(tmp_path / "box.npz")
    voxels, _ = full.voxels()
    centers = full.voxel_centers(voxels.index)
    inside = np.all((centers >= bounds[0]) & (centers <= bounds[1]), axis=1)
    np.testing.assert_array_equal(box.voxels()[0].index, voxels.index[inside])
    assert report["tiles_read"] < info["tiles"]
    # the viewer: a decimated overview of every tile, one tile in full
    from evsemmap_warp.apps.viewer import MapViewer, free_port

    viewer = MapViewer([tmp_path / "ab_store"], port=free_port(), max_voxels=2000)
    try:
        overview = len(viewer.layers[0].centers)
        assert overview <= 2000 + len(viewer.stores[0].parts)
        tile = sorted(viewer.stores[0].store.tiles, key=lambda t: -viewer.stores[0].store.tiles[t]["voxels"])[0]
        viewer.tiles.show(f"0: {tile}")
        assert len(viewer.layers[0].centers) >= overview + viewer.stores[0].store.tiles[tile]["voxels"] - len(viewer.stores[0].parts[tile]["state"])
        layer = viewer.layers[0]
        np.testing.assert_array_equal(layer.voxel_at(layer.centers[::37]), np.arange(len(layer.centers))[::37])  # picking works
    finally:
        viewer.server.stop()


def test_a_rerun_after_the_learned_lengths_changed_is_refused_not_mixed(drive, tmp_path):
    """The mapping names the lengths' file; the same name with other lengths in it would have resumed, adding chunks
    mapped with the new gains to those mapped with the old."""
    lengths, settings = tmp_path / "lengths.json", tmp_path / "learned.yaml"
    settings.write_text(f"mapping:\n  convbki:\n    lengths_file: {lengths}\n")
    classes = open_dataset(load_config([str(drive)]).dataset).num_classes
    lengths.write_text(json.dumps({"ell_h": [0.5] * classes, "ell_z": [0.5] * classes}))
    _batch([drive, settings], tmp_path / "store", "ebs-learned", executor="inline", chunk_frames=2)
    _batch([drive, settings], tmp_path / "store", "ebs-learned", executor="inline", chunk_frames=2)  # the same lengths: resumes
    lengths.write_text(json.dumps({"ell_h": [0.3] + [0.5] * (classes - 1), "ell_z": [0.5] * classes}))
    with pytest.raises(ConfigError, match=r"holds a batch run of other inputs or settings \(differing: learned_lengths\)"):
        _batch([drive, settings], tmp_path / "store", "ebs-learned", executor="inline", chunk_frames=2)


def test_configurations_that_cannot_work_stop_before_any_work(drive, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(planning, "available_memory", lambda: 1 << 30)
    # the automatic chunk size is named as such; not even one-scan chunks fit 4 workers in 1 GB, so only fewer workers help
    with pytest.raises(ConfigError, match=r"--chunk-frames 1 \(chosen automatically\) with 4 workers needs about .* GB .* use fewer --workers"):
        _batch([drive], tmp_path / "small", workers=4)
    assert not (tmp_path / "small").exists()
    monkeypatch.undo()
    _batch([drive], tmp_path / "store", executor="inline", chunk_frames=2)
    with pytest.raises(ConfigError, match="holds a batch run of other inputs or settings .differing: mapping, method"):
        _batch([drive], tmp_path / "store", "s-csm", executor="inline", chunk_frames=2)
    monkeypatch.setitem(sys.modules, "ray", None)
    assert main(["batch", str(drive), "--method", "ebs", "--out", str(tmp_path / "r"), "--executor", "ray", "--quiet"]) == 2
    assert 'pip install "evsemmap_warp[ray]"' in capsys.readouterr().err
    assert main(["batch", str(drive), "--method", "ebs", "--out", str(tmp_path / "x"), "--ray-address", "auto"]) == 2
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "store.json").write_text("{not json")
    with pytest.raises(StoreError, match="not a readable store index"):
        MapStore(tmp_path / "junk")
    assert main(["merge", str(tmp_path / "store"), "--out", str(tmp_path / "m.npz")]) == 2


def test_a_corridor_world_is_seamless_and_long_drives_need_only_tiles_in_view(tmp_path):
    from evsemmap_warp.synthetic.scene import generate_world
    from evsemmap_warp.synthetic.writer import sequence_poses

    preset = load_preset("long", world__size_m=30, world__corridor_tiles=3, trajectory__frames=120, trajectory__spacing_m=0.5,
                         trajectory__margin_m=5, lidar__max_range_m=15)
    tiles = [generate_world(preset.world, preset.seed, tile=t) for t in range(2)]
    seam = [w.vertices[np.isclose(w.vertices[:, 0], 15.0) & (np.abs(w.vertices[:, 1]) < 14.5)] for w in tiles]
    ground = [s[np.argsort(s[:, 1])][:, 1:] for s in seam]
    assert len(ground[0]) > 50
    np.testing.assert_allclose(ground[0], ground[1], atol=0.05)  # the terrain meets at the seam (puddles may dip 3 cm)
    poses = sequence_poses(preset)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert len(poses) == 120 and poses[-1, 0, 3] > 30 and steps.max() < 0.6  # across two seams, no jump
    summary = generate_sequence(preset, tmp_path / "long", progress=False, camera=False)
    assert summary["frames"] == 120 and not summary["camera"] and summary["drive_m"] > 55
    assert summary["triangles"] < 3.5 * len(tiles[0].faces)  # a window of tiles, never the whole corridor
    assert not (tmp_path / "long" / "pylon_camera_node").exists()
    # every scan equals one of the whole corridor held at once: the window held every tile in range
    from evsemmap_warp.synthetic.scene import concatenate_worlds
    from evsemmap_warp.synthetic.sensors import RayCaster, lidar_directions, scan_lidar

    whole = concatenate_worlds([generate_world(preset.world, preset.seed, tile=t) for t in range(3)])
    caster = RayCaster(whole.vertices, whole.faces)
    for index in range(0, 120, 7):
        scan = scan_lidar(caster, whole, poses[index], preset.lidar, np.random.default_rng([preset.seed, index]), lidar_directions(preset.lidar))
        written = np.fromfile(tmp_path / "long" / "os1_cloud_node_kitti_bin" / f"{index:06d}.bin", np.float32).reshape(-1, 4)
        np.testing.assert_array_equal(written, scan.points)


def test_pool_workers_start_with_math_libraries_at_their_share_of_the_cores(drive, tmp_path, monkeypatch):
    """Every worker's BLAS used every core (the point transforms): two workers on two cores ran their
    chunks slower than with one thread each. The driver's own environment is left as it was."""
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")  # a user's own setting is kept
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    executor = batch.LocalExecutor(2, _pool_context(drive, tmp_path / "store"))
    seen = []
    try:
        executor.run(os.getenv, [("OPENBLAS_NUM_THREADS",), ("MKL_NUM_THREADS",)], lambda item, value: seen.append((item[0], value)))
    finally:
        executor.close()
    assert sorted(seen) == [("MKL_NUM_THREADS", "3"), ("OPENBLAS_NUM_THREADS", "1")]
    assert "OPENBLAS_NUM_THREADS" not in os.environ and os.environ["MKL_NUM_THREADS"] == "3"


def test_a_pool_worker_that_dies_as_it_starts_fails_the_run_and_never_hangs_it(drive, tmp_path):
    """A script that starts a pool at its top level, with no ``if __name__ == "__main__":``: each worker runs the
    script again as it starts and dies there, before reading what the driver sends it: a context larger than a pipe
    holds (a drive of 300 frames or more), written into its start-up pipe, would block the driver for ever. The run
    fails, saying why, in bounded time."""
    script = tmp_path / "unguarded.py"
    script.write_text(f"""
import os
from pathlib import Path
from evsemmap_warp.apps import batch
from evsemmap_warp.apps.batch import BatchOptions
store = Path({str(tmp_path / "store")!r})
_, sources, config, _, _ = batch.plan_batch([{str(drive)!r}], BatchOptions(method="ebs", out=store))
origin_index, class_names, *_ = batch.probe(sources, config)
context = batch.Context(store, sources, config, sources[0].num_classes, class_names, origin_index, 256)
context.sources_as_large_as_a_long_drive_s = bytes(1 << 20)
executor = batch.LocalExecutor(1, context, retries=1)
try:
    executor.run(os.getenv, [("HOME",)], lambda item, value: None)
finally:
    executor.close()
""")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    try:
        done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=180, cwd=tmp_path,
                              env={**os.environ, "TMPDIR": str(scratch)})
    except subprocess.TimeoutExpired:
        pytest.fail("the driver hung on a worker that died as it started")
    assert done.returncode != 0
    assert "a worker died 2 times" in done.stderr and 'if __name__ == "__main__"' in done.stderr, done.stderr[-3000:]
    assert not list(scratch.iterdir())  # the context's file is gone with the pool


def test_a_temporary_folder_the_pools_context_cannot_go_to_is_named(drive, tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "absent"))
    executor = batch.LocalExecutor(1, _pool_context(drive, tmp_path / "store"))
    try:
        with pytest.raises(OSError, match=r"writing the run's context for the pool's workers; TMPDIR sets the folder.*absent"):
            executor.run(os.getenv, [("HOME",)], lambda item, value: None)
    finally:
        executor.close()


def test_pool_workers_of_a_run_without_a_network_do_not_import_torch(drive, tmp_path):
    """Importing torch costs a worker process about 1.5 s of CPU, out of the mapping's time where the
    workers share the cores; only scans labelled by a checkpoint need it."""
    executor = batch.LocalExecutor(1, _pool_context(drive, tmp_path / "store"))
    seen = []
    try:
        executor.run(eval, [("'torch' in __import__('sys').modules",)], lambda item, value: seen.append(value))
    finally:
        executor.close()
    assert seen == [False]


def test_a_workers_time_is_told_by_stage(drive, tmp_path):
    """map_chunk's stages (open, read, integrate, extract, write_partial) are all there, none negative,
    and add up to no more than the chunk's seconds; the summary gives their medians and sums, and the
    pool's hand-off costs (a worker process's start, the result's size and way back)."""
    options = BatchOptions(method="ebs", out=tmp_path / "inline", executor="inline", chunk_frames=2, progress=False)
    summary = run_batch([str(drive)], options, log=lambda m: None)
    assert set(summary["chunk_stage_seconds_median"]) == set(batch.CHUNK_STAGES) == set(summary["chunk_stage_seconds_total"])
    assert summary["chunk_handoff"] is None  # inline: no process boundary
    # the driver's fold rate is voxels_folded / seconds.fold: every chunk's partial voxels, each stored voxel at least once
    store = json.loads((tmp_path / "inline" / "store.json").read_text())
    assert summary["voxels_folded"] == sum(c["voxels"] for c in store["chunks"]) > summary["voxels"]
    inputs, sources, config, chunks, identity = batch.plan_batch([str(drive)], options)
    origin_index, class_names, *_ = batch.probe(sources, config)
    context = batch.Context(tmp_path / "direct", sources, config, sources[0].num_classes, class_names, origin_index, 256, frame=sources[0].frame)
    (tmp_path / "direct" / "work").mkdir(parents=True)
    for record in [batch.map_chunk(chunk, context) for chunk in chunks]:
        stages = record["stage_seconds"]
        assert list(stages) == list(batch.CHUNK_STAGES)
        assert all(v >= 0 for v in stages.values()), stages
        assert sum(stages.values()) <= record["seconds"] + 1e-3, (stages, record["seconds"])
        assert stages["integrate"] > 0 and stages["write_partial"] > 0
    pooled = _batch([drive], tmp_path / "pool", executor="local", workers=1, chunk_frames=2)
    assert pooled["voxels_folded"] == summary["voxels_folded"]
    handoff = pooled["chunk_handoff"]
    assert handoff["worker_start_s_median"] > 0 and handoff["result_kb_median"] > 0 and handoff["return_s_median"] >= 0
    assert set(pooled["chunk_stage_seconds_median"]) == set(batch.CHUNK_STAGES)
    _assert_same_bytes(tmp_path / "inline", tmp_path / "pool")  # timing changes nothing in the store


def test_bench_batch_gives_the_drivers_fold_rate_and_the_worker_count_it_limits(monkeypatch):
    """The driver keeps up while workers x one worker's voxel rate stays under its fold rate: with 20 s of
    mapping against 3 s of folding, from 6 workers on it does not (issue 49's bottleneck count)."""
    monkeypatch.syspath_prepend(str(REPO / "tools"))
    import bench_batch

    row = {"fold_s": 3.0, "voxels_folded": 6_000_000, "chunk_stage_s_total": {"open": 0.5, "read": 2.0, "integrate": 15.0, "extract": 2.0,
                                                                              "write_partial": 0.5}}
    fold = bench_batch.fold_bottleneck(row, 2000)
    assert fold["voxels_per_s"] == 2_000_000 and fold["worker_voxels_per_s"] == 300_000 and fold["bottleneck_workers"] == 6
    assert fold["long_drive"] == {"frames": bench_batch.LONG_DRIVE_FRAMES, "fold_s": 7.5, "worker_s": 50.0}
    # with fold lanes the driver only hands out and writes (0.5 s); two lanes fold 8 s between them: the
    # busier share is a lane's 4 s, so 5 workers; one lane keeps up with 2 workers, the driver alone with 40
    lanes = bench_batch.fold_bottleneck(row | {"fold_s": 0.5, "fold_lanes": {"width": 2, "lane_seconds": 8.0}}, 2000)
    assert lanes["voxels_per_s"] == 1_500_000 and lanes["driver_voxels_per_s"] == 12_000_000 and lanes["lane_voxels_per_s"] == 750_000
    assert (lanes["bottleneck_workers"], lanes["workers_per_lane"], lanes["driver_limit_workers"]) == (5, 2, 40)


def test_bench_batch_s_two_node_row_compares_the_stores_and_is_skipped_saying_why(monkeypatch, tmp_path, capsys):
    """The two-node row stands only on a store byte-identical to the local pool's (store_differences names the files
    that differ), and where this machine allows no mount namespace it is skipped with the reason, recorded."""
    monkeypatch.syspath_prepend(str(REPO / "tools"))
    import bench_batch
    import ray_cluster

    for store, tile in (("a", b"tile"), ("b", b"tile"), ("c", b"other")):
        (tmp_path / store / "tiles").mkdir(parents=True)
        (tmp_path / store / "tiles" / "0_0_0.vox").write_bytes(tile)
    (tmp_path / "c" / "store.json").write_text("{}")
    assert bench_batch.store_differences(tmp_path / "a", tmp_path / "b") == []
    assert bench_batch.store_differences(tmp_path / "a", tmp_path / "c") == ["store.json", "tiles/0_0_0.vox"]
    monkeypatch.setattr(ray_cluster, "mount_namespaces_refused", lambda folder: "a private mount namespace is not allowed here (EPERM)")
    results = {"runs": {}}
    bench_batch.two_node_rows(results, tmp_path / "data", tmp_path, tmp_path / "warm", [], None, {}, tmp_path / "local")
    assert results == {"runs": {}, "skipped": {"ray-2node": "a private mount namespace is not allowed here (EPERM)"}}
    assert "batch ray-2node: skipped: a private mount namespace is not allowed here" in capsys.readouterr().out
