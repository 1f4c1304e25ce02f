"""Batch on a real Ray cluster of two nodes on the loopback, whose second node shares no files with the driver
(tools/ray_cluster.py): the store is byte-identical to the local pool's with every node up, with replicated inputs,
with a node stopped mid-run and after the driver was killed; a node with another version of the project, a lost
head and a lost input are one line each. The driver is the command line, in a process of its own, as a user runs it."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO

import evsemmap_warp
import evsemmap_warp.files
from evsemmap_warp.apps.batch import BatchOptions, ray_executor, run_batch, worker
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

sys.path.insert(0, str(REPO / "tools"))
from ray_cluster import TwoNodeCluster, mount_namespaces_refused  # noqa: E402

ray = pytest.importorskip("ray")
RUN_TIMEOUT_S = 300


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """The cluster, the driver's input folder (the tiny drive in it) and store folder, both hidden from the second
    node, and the local pool's store of the drive to compare with."""
    root = tmp_path_factory.mktemp("cluster")
    data, stores = root / "data", root / "stores"
    data.mkdir()
    stores.mkdir()
    refused = mount_namespaces_refused(data)
    if refused:
        pytest.skip(refused)
    generate_sequence(load_preset("tiny"), data / "drive", progress=False)
    run_batch([str(data / "drive")], BatchOptions(method="ebs", out=stores / "local", workers=2, chunk_frames=1, progress=False),
              log=lambda m: None)
    cluster = TwoNodeCluster([data, stores])
    cluster.data, cluster.stores = data, stores
    yield cluster
    cluster.close()


def _assert_same_bytes(a: Path, b: Path) -> None:
    """Stores ``a`` and ``b`` hold the same files, byte for byte."""
    def read(store):
        return {str(p.relative_to(store)): p.read_bytes() for p in sorted(store.rglob("*")) if p.is_file()}

    files_a, files_b = read(a), read(b)
    assert sorted(files_a) == sorted(files_b)
    assert [name for name in files_a if files_a[name] != files_b[name]] == []


def _driver(cluster, out, drive=None, chunk_frames=1, settings=(), method="ebs", options=()) -> subprocess.Popen:
    """``evsemmap batch`` of ``drive`` (default: the tiny drive) and ``settings`` (config files) on the cluster, two workers,
    and the command's ``options``."""
    command = [sys.executable, "-m", "evsemmap_warp", "batch", str(drive or cluster.data / "drive"), *map(str, settings), "--method", method,
               "--out", str(out), "--executor", "ray", "--ray-address", cluster.address, "--workers", "2", "--quiet"]
    command += (["--chunk-frames", str(chunk_frames)] if chunk_frames else []) + list(options)
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ | cluster.env)


def _communicate(driver: subprocess.Popen) -> tuple[str, str]:
    """The driver's output once it ends; a driver past RUN_TIMEOUT_S is killed, not left running."""
    try:
        return driver.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        driver.kill()
        driver.communicate(timeout=30)
        raise


def _finish(driver: subprocess.Popen) -> tuple[dict, str]:
    out, err = _communicate(driver)
    assert driver.returncode == 0, err
    return json.loads(out), err


def _failure(driver: subprocess.Popen) -> str:
    """The one line a failed run says (exit 2, no traceback)."""
    _, err = _communicate(driver)
    lines = [line for line in err.splitlines() if line.startswith("evsemmap: error:")]
    assert driver.returncode == 2 and len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _wait_for_a_chunk(driver: subprocess.Popen, out) -> None:
    """Until the driver has written its first chunk (the others are in flight, or queued)."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while not list((out / "work").glob("chunk_*")):
        if driver.poll() is not None or time.monotonic() >= deadline:
            driver.kill()
            _, err = driver.communicate(timeout=30)
            raise AssertionError(f"the driver wrote no chunk (exit {driver.returncode}): {err[-2000:]}")
        time.sleep(0.05)


def test_a_cluster_whose_second_node_sees_no_files_writes_the_local_pools_store(cluster):
    summary, _ = _finish(_driver(cluster, cluster.stores / "ray"))
    _assert_same_bytes(cluster.stores / "local", cluster.stores / "ray")
    assert summary["cluster"]["nodes"] == 2 and summary["cluster"]["inputs"] == "from the driver"
    assert "does not see " + str(cluster.data / "drive") in summary["cluster"]["inputs_why"]
    assert len(summary["cluster"]["chunks_per_node"]) == 2  # both nodes mapped chunks


def test_replicated_inputs_are_read_at_the_same_path(cluster):
    """A node with its own copy of the inputs at the driver's paths (replicated data, not shared) reads them there."""
    cluster.stop(cluster.node)
    cluster.node = cluster.start_node(replicated=cluster.data)
    for attempt in range(3):
        # a node just joined may not yet be in the head's view of free CPUs: the head then maps every tiny chunk
        out = cluster.stores / f"replicated{attempt}"
        summary, _ = _finish(_driver(cluster, out))
        _assert_same_bytes(cluster.stores / "local", out)
        assert summary["cluster"]["nodes"] == 2 and summary["cluster"]["inputs"] == "same path"
        if len(summary["cluster"]["chunks_per_node"]) == 2:
            break
    assert len(summary["cluster"]["chunks_per_node"]) == 2  # the node with the copy mapped chunks from it


def test_a_node_without_the_learned_lengths_is_refused_at_the_start_naming_it(cluster):
    """Workers read the learned lengths (ebs-learned, convbki) at the mapping's path, also where the driver sends the
    scans: a node without them, or with other lengths there, would fail or map with other gains."""
    classes = len(json.loads((cluster.stores / "local" / "store.json").read_text())["classes"])
    lengths, settings = cluster.data / "lengths.json", cluster.data / "learned.yaml"
    lengths.write_text(json.dumps({"ell_h": [0.5] * classes, "ell_z": [0.5] * classes}))
    settings.write_text(f"mapping:\n  convbki:\n    lengths_file: {lengths}\n")
    out = cluster.stores / "learned"
    line = _failure(_driver(cluster, out, settings=[settings], method="ebs-learned"))
    assert re.search(rf"node .* does not see the learned lengths {re.escape(str(lengths))} .*give every node that file at the same path",
                     line), line
    assert not list(out.rglob("chunk_*"))


@pytest.mark.parametrize("version, said", [
    ("0.0.9", rf"node .* has evsemmap_warp 0\.0\.9, the driver {evsemmap_warp.__version__}: install the same version"),
    (None, rf"node .* cannot run this project's tasks \(.*\): install evsemmap_warp {evsemmap_warp.__version__}, the driver's"),
])
def test_a_node_with_another_version_or_none_is_refused_at_the_start_naming_it(cluster, tmp_path, version, said):
    """A third node sees, at the project's path, its code under another version number (its __init__.py bound over),
    or an empty folder."""
    package = Path(evsemmap_warp.__file__).parent
    if version:
        (tmp_path / "init.py").write_text((package / "__init__.py").read_text() + f"\n__version__ = {version!r}\n")
    third = cluster.start_node(installed={package / "__init__.py": tmp_path / "init.py"} if version else {package: None})
    out = cluster.stores / f"refused_{version}"
    try:
        line = _failure(_driver(cluster, out))
    finally:
        cluster.stop(third)
    assert re.search(said, line), line
    assert not list(out.rglob("chunk_*"))  # refused before any chunk


def test_a_killed_driver_s_rerun_resumes_into_the_local_pools_store(cluster):
    out = cluster.stores / "driver_killed"
    driver = _driver(cluster, out)
    _wait_for_a_chunk(driver, out)
    driver.send_signal(signal.SIGKILL)
    driver.wait(timeout=30)
    summary, _ = _finish(_driver(cluster, out))
    assert summary["chunks_resumed"] >= 1
    _assert_same_bytes(cluster.stores / "local", out)


def test_a_node_stopped_mid_run_costs_its_chunks_a_retry_and_nothing_else(cluster):
    """Stopped while it runs a chunk: the ``default`` drive, LiDAR only (15 chunks of about half a second; rendering
    its camera took most of a minute), whose tasks last long enough to see one running on the second node. The
    tiles fold in two lanes, one on each node: the stopped node's lane, and the tiles in its memory, are rebuilt on
    the head from the partials they absorbed since their last write."""
    generate_sequence(load_preset("default"), cluster.data / "default", progress=False, camera=False)
    run_batch([str(cluster.data / "default")], BatchOptions(method="ebs", out=cluster.stores / "default_local", workers=2,
                                                            progress=False), log=lambda m: None)
    out = cluster.stores / "node_stopped"
    driver = _driver(cluster, out, cluster.data / "default", chunk_frames=None, options=["--fold-workers", "2"])
    _wait_for_a_chunk(driver, out)
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while not cluster.runs_a_task(cluster.node):
        assert driver.poll() is None and time.monotonic() < deadline, "the second node ran no chunk after the first"
        time.sleep(0.05)
    cluster.stop(cluster.node)
    summary, err = _finish(driver)
    _assert_same_bytes(cluster.stores / "default_local", out)
    # Ray's own notice (on stderr: stdout carries the summary alone) of the lost node's work: a task still running
    # "will be retried"; a task done whose result lived on the node is run again ("Attempting to recover lost objects")
    assert re.search(r"will be retried|Attempting to recover", err), err[-2000:]
    assert sum(summary["cluster"]["chunks_per_node"].values()) == summary["chunks"]
    assert summary["fold_lanes"]["restarts"] >= 1  # 2 when the first successor went to the node before Ray saw it gone


def test_a_lost_head_is_one_line_and_keeps_the_chunks_mapped(cluster):
    """The last test of the module: the cluster is gone after it."""
    out = cluster.stores / "head_lost"
    driver = _driver(cluster, out)
    _wait_for_a_chunk(driver, out)
    cluster.stop(cluster.head)
    line = _failure(driver)
    assert "lost the connection to the Ray cluster" in line and "rerun resumes" in line, line
    assert list((out / "work").glob("chunk_*"))


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_an_input_gone_during_a_run_on_this_machine_is_the_missing_file_as_the_os_names_it(tmp_path, executor):
    """A local Ray instance's one node is this machine, whose files no probe checked: an input deleted during the run
    (here: after the first chunk) is the missing file, as the pool says it, not a cluster's node said to lack it."""
    generate_sequence(load_preset("tiny"), tmp_path / "drive", progress=False)
    gone = sorted((tmp_path / "drive").rglob("*.bin"))[-1]

    def delete_once(name, voxels):
        gone.unlink(missing_ok=True)

    with pytest.raises(FileNotFoundError) as error:
        run_batch([str(tmp_path / "drive")], BatchOptions(method="ebs", out=tmp_path / "store", executor=executor, workers=1,
                                                          chunk_frames=1, progress=False), log=lambda m: None, on_tile=delete_once)
    assert error.value.filename == str(gone) and not isinstance(error.value, ray_executor.ClusterError)


def test_a_node_without_an_input_the_probe_found_on_every_node_is_named_with_the_file(tmp_path):
    """Where the probe found the inputs at the driver's paths on every node, a task's missing input names its node and
    the file; a missing file that is no input (the node's scratch folder, say) is left as it is."""
    missing = FileNotFoundError(2, "No such file or directory", str(tmp_path / "drive" / "velodyne" / "000005.bin"))
    said = ray_executor.missing_input(missing, "n2 (10.0.0.2, node 1234abcd)", [str(tmp_path / "drive"), str(tmp_path / "alpha")])
    assert isinstance(said, ray_executor.ClusterError)
    assert str(said).startswith(f"node n2 (10.0.0.2, node 1234abcd) does not see the input file {missing.filename}, which the probe at "
                                f"the start found at the same path on every node (removed since, or a node that joined later?): ")
    for other in (tmp_path / "drive2" / "000005.bin", Path("/tmp/evsemmap-batch-0123/work/.chunk_000005.77.tmp")):
        elsewhere = FileNotFoundError(2, "No such file or directory", str(other))
        assert ray_executor.missing_input(elsewhere, "n2", [str(tmp_path / "drive")]) is elsewhere
    assert ray_executor.missing_input(missing, "n2", None) is missing  # no probe ran (a local instance)


def test_what_killed_tasks_left_in_a_nodes_scratch_folder_goes_with_its_next_task(tmp_path):
    """A task killed on a node (a stuck one cancelled, a worker out of memory) leaves its temporary chunk folder in the
    node's scratch folder, which then never emptied, and stayed; the next task there removes it, not a live task's,
    and not one of a process in another PID namespace (another node's, sharing the folder), dead here or not."""
    namespace, _, me = worker.process_tag().rpartition("-")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True).stdout.strip()
    (tmp_path / "work" / f".chunk_000003.{namespace}-{dead}.tmp").mkdir(parents=True)
    (tmp_path / "work" / f".chunk_000003.{namespace}-{dead}.tmp" / "0_0_0.vox").write_bytes(b"half a file")
    alive = [f".chunk_000004.{namespace}-{me}.tmp", f".chunk_000005.{namespace}1-{dead}.tmp"]  # ...1: another namespace
    for name in alive:
        (tmp_path / "work" / name).mkdir()
    ray_executor.remove_dead_tasks_leftovers(tmp_path)
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == sorted(alive)


def test_a_full_object_store_is_one_line_saying_what_to_change():
    """Ray's ObjectStoreFullError, from the driver's put (scans sent) or a task's result, as one line."""
    executor = object.__new__(ray_executor.RayExecutor)

    class FullRay:
        exceptions = ray.exceptions

        @staticmethod
        def put(value):
            raise ray.exceptions.ObjectStoreFullError("Failed to put object ffff in object store because it is full. Object size is 9 MB.")

        get = put

    executor.ray = FullRay
    for call in (executor.put, executor._receive):
        with pytest.raises(ray_executor.ClusterError, match=r"^Ray's object store is full \(ObjectStoreFullError: Failed to put object "
                                                            r"ffff in object store because it is full\): .* fewer --workers"):
            call(None)


def test_inputs_are_read_at_the_same_path_only_where_every_node_holds_the_same_content(tmp_path):
    """A stale copy at the driver's path (other content) counts as no copy: the driver sends the scans."""
    (tmp_path / "drive").mkdir()
    (tmp_path / "drive" / "000000.bin").write_bytes(b"scan")
    plan = {"inputs": [[evsemmap_warp.files.content_identity(tmp_path / "drive"), {"path": str(tmp_path / "preset.yaml")}]],
            "payload": {"checkpoint": None, "alpha": None, "bin_frames": None}}
    inputs = ray_executor.probed_inputs(plan)
    assert list(inputs) == [str(tmp_path / "drive")]  # the configs are the driver's to read
    executor = object.__new__(ray_executor.RayExecutor)
    executor.own_instance = False
    same = {"node": "a", "inputs": {str(tmp_path / "drive"): evsemmap_warp.files.content_identity(tmp_path / "drive")}}
    executor._probe = lambda probed: [same, same | {"node": "b"}]
    assert executor._choose_inputs(inputs)[:2] == (2, "same path")
    (tmp_path / "drive" / "000000.bin").write_bytes(b"another scan")
    stale = {"node": "b", "inputs": {str(tmp_path / "drive"): evsemmap_warp.files.content_identity(tmp_path / "drive")}}
    executor._probe = lambda probed: [same, stale]
    assert executor._choose_inputs(inputs) == (2, "from the driver", f"node b sees other content at {tmp_path / 'drive'}: the driver "
                                                                      f"reads and sends each chunk's scans")
    (tmp_path / "empty").mkdir()  # where a node's data folder is a mount point with nothing mounted
    empty = {"node": "b", "inputs": {str(tmp_path / "drive"): evsemmap_warp.files.content_identity(tmp_path / "empty")}}
    executor._probe = lambda probed: [same, empty]
    assert executor._choose_inputs(inputs)[2].startswith(f"node b sees an empty folder at {tmp_path / 'drive'}: ")
