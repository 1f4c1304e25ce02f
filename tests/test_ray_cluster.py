"""Batch on a real two-node Ray cluster whose second node shares no files with the driver (tests/ray_cluster.py):
the store is byte-identical to the local pool's, with every node up and with a node stopped mid-run. The driver
is the command line, in a process of its own, as a user runs it."""

import json
import os
import subprocess
import sys
import time

import pytest

from ray_cluster import TwoNodeCluster, mount_namespaces_refused
from test_batch import _assert_same_bytes, _batch
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

pytest.importorskip("ray")
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
    _batch([data / "drive"], stores / "local", executor="local", workers=2, chunk_frames=1)
    cluster = TwoNodeCluster([data, stores])
    cluster.data, cluster.stores = data, stores
    yield cluster
    cluster.close()


def _driver(cluster, out, *flags) -> subprocess.Popen:
    command = [sys.executable, "-m", "evsemmap_warp", "batch", str(cluster.data / "drive"), "--method", "ebs", "--out", str(out),
               "--executor", "ray", "--ray-address", cluster.address, "--workers", "2", "--chunk-frames", "1", "--quiet", *flags]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ | cluster.env)


def _finish(driver: subprocess.Popen) -> dict:
    out, err = driver.communicate(timeout=RUN_TIMEOUT_S)
    assert driver.returncode == 0, err
    return json.loads(out), err


def test_a_cluster_whose_second_node_sees_no_files_writes_the_local_pools_store(cluster):
    summary, _ = _finish(_driver(cluster, cluster.stores / "ray"))
    _assert_same_bytes(cluster.stores / "local", cluster.stores / "ray")
    assert summary["cluster"]["nodes"] == 2 and summary["cluster"]["inputs"] == "from the driver"
    assert len(summary["cluster"]["chunks_per_node"]) == 2  # both nodes mapped chunks


def test_a_node_stopped_mid_run_costs_its_chunks_a_retry_and_nothing_else(cluster):
    out = cluster.stores / "node_stopped"
    driver = _driver(cluster, out)
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while not list((out / "work").glob("chunk_*")):  # the first chunk is in: the second node holds others
        assert driver.poll() is None and time.monotonic() < deadline, driver.communicate()
        time.sleep(0.05)
    cluster.stop_node()
    summary, err = _finish(driver)
    _assert_same_bytes(cluster.stores / "local", out)
    assert "will be retried" in err  # Ray's own notice (on stderr: stdout carries the summary alone) of the lost node's task
    assert sum(summary["cluster"]["chunks_per_node"].values()) == summary["chunks"]
