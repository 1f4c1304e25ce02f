"""Fresh table rows are faulted in once, by a write: on Linux a page of the CPU row reservation that a kernel
reads first maps the shared zero page and faults again on the write that follows, and two shards' faults
contend in the kernel, so every kernel that adds to a row marks it touched first (docs/performance.md,
``kernels/scatter.py``, ``touch_row``). Counted with the launching thread's minor faults (one worker: the
launches run on the calling thread)."""

from __future__ import annotations

import resource
import sys

import numpy as np
import pytest

from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings
from evsemmap_warp.core import voxel_map as vm
from evsemmap_warp.core.mapper import Mapper

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or not hasattr(resource, "RUSAGE_THREAD"),
                                reason="counts Linux's per-thread page faults")


def _ground_scan(rng, n, half_width):
    """Points on a bumpy 2 x half_width m square around the sensor, random labels of 5 classes."""
    xy = rng.uniform(-half_width, half_width, (n, 2))
    z = 0.3 * np.sin(xy[:, 0] / 3.0) + rng.normal(0, 0.05, n)
    return np.c_[xy, z], rng.integers(0, 5, n)


def test_the_block_gather_faults_its_fresh_rows_in_once(monkeypatch):
    config = MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
                           compat=Compat.SBKI, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                           sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=100.0, max_range_m=None))
    mapper = Mapper(config, 5, workers=1)
    faults = {"gather": 0}
    launch = vm.wp.launch

    def counted(kernel, *args, **kwargs):  # the gather kernels' launches only: growing a table faults its new slots in at once
        if "gather" not in kernel.key:
            return launch(kernel, *args, **kwargs)
        before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        try:
            return launch(kernel, *args, **kwargs)
        finally:
            faults["gather"] += resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before

    monkeypatch.setattr(vm.wp, "launch", counted)
    rng = np.random.default_rng(0)
    mapper.integrate(*_ground_scan(rng, 2000, 5.0), payload_type="label", sensor_origin=np.zeros(3))  # compiles, warms up
    rows_before, faults["gather"] = mapper.voxel_count, 0
    for shift in (30.0, 60.0):  # new ground: every row these scans add is fresh memory
        points, labels = _ground_scan(rng, 60_000, 12.0)
        mapper.integrate(points + [shift, 0.0, 0.0], labels, payload_type="label", sensor_origin=np.array([shift, 0.0, 1.5]))
    new_rows = mapper.voxel_count - rows_before
    row_pages = new_rows * (5 + vm.EXTRA_COLUMNS) * 8 / resource.getpagesize()
    assert row_pages > 500, "too few new rows to tell one fault per page from two"
    # read first, each fresh page faults twice (2.0x); written first, once, plus the brick cache's new entries
    assert faults["gather"] < 1.3 * row_pages, f"{faults['gather']} faults for {row_pages:.0f} pages of new rows"


def test_the_read_out_leaves_numpys_huge_page_advice_as_the_process_has_it():
    # The advice is numpy's process-wide setting (NUMPY_MADVISE_HUGEPAGE): a library call must not change
    # it, on its own thread or on the user's others.
    numpy_switch = getattr(getattr(np, "_core", None), "multiarray", None)
    switch = getattr(numpy_switch, "_set_madvise_hugepage", None)
    if switch is None:
        pytest.skip("this numpy has no huge-page advice switch")
    seen = []
    real_summarize = Mapper.summarize

    def summarize(self, evidence, touched):
        seen.append(bool(switch(True)))  # returns the setting in force (and leaves it on)
        return real_summarize(self, evidence, touched)

    before = bool(switch(True))
    try:
        mapper = Mapper(MappingConfig(method="ebs"), 5, workers=1)
        rng = np.random.default_rng(0)
        mapper.integrate(rng.uniform(-2, 2, (500, 3)), rng.gamma(1.0, 2.0, (500, 5)) + 1.0, payload_type="alpha", sensor_origin=np.zeros(3))
        Mapper.summarize = summarize
        mapper.voxels()
        assert seen == [True] and switch(True) is True
    finally:
        Mapper.summarize = real_summarize
        switch(before)


def test_the_command_line_turns_the_huge_page_advice_off_for_its_own_process_only_unless_told(tmp_path):
    # The command line is a program of its own: it makes the read-out's choice for its process (the
    # environment's NUMPY_MADVISE_HUGEPAGE, which numpy reads at import), and a run that sets the variable keeps it.
    import os
    import subprocess

    probe = ("import sys; sys.argv = ['evsemmap', 'dump-config', 'ebs']; import evsemmap_warp.__main__ as m; "
             "m.main(); import numpy; print('advice', numpy._core.multiarray._set_madvise_hugepage(False))")
    environment = {key: value for key, value in os.environ.items() if key != "NUMPY_MADVISE_HUGEPAGE"}
    for setting, expected in ((None, "advice False"), ("1", "advice True")):
        env = environment if setting is None else environment | {"NUMPY_MADVISE_HUGEPAGE": setting}
        done = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        assert done.stdout.strip().splitlines()[-1] == expected
