"""Shared test set-up: a predictable Warp kernel cache, the device list, the shared data folder."""

import os
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("WARP_CACHE_PATH", str(REPO / ".warp_cache"))

SHARED = REPO.parent / "shared"
TOY_DIR = REPO / "tests" / "data" / "sbki_toy"


def available_devices() -> list[str]:
    from evsemmap_warp.core.warp_runtime import init_warp

    wp = init_warp()
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


DEVICES = available_devices()


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param


SHARED_SKIP_REASON = "this test needs the project's shared data folder beside the checkout (CI has it)"


def shared_path(*parts: str) -> Path:
    """A path under ../shared, or a skip that says why when the checkout has no ../shared."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is absent: {SHARED_SKIP_REASON}")
    return path


def pytest_runtest_logreport(report):
    # .ci/run runs the suite with ../shared hidden, as on a plain clone, then runs again, with ../shared, the
    # tests that skipped for want of it: their node ids go to the file EVSEMMAP_SHARED_SKIPS names.
    record = os.environ.get("EVSEMMAP_SHARED_SKIPS")
    if record and report.skipped and isinstance(report.longrepr, tuple) and SHARED_SKIP_REASON in str(report.longrepr[2]):
        with open(record, "a") as out:
            out.write(report.nodeid + "\n")


def run_cli(capsys, *argv) -> str:
    """Run the CLI in this process; assert exit 2 and one line on stderr without a traceback; return that line."""
    from evsemmap_warp.apps.cli import main

    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        code = exc.code
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("Warp CUDA warning")]
    assert code == 2, err
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def wait_until(predicate, timeout: float, interval: float = 0.05) -> bool:
    """Whether ``predicate()`` came true within ``timeout`` seconds (asked every ``interval``): the viewer tests wait
    on threads, servers and browsers this way."""
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        time.sleep(interval)
    return False


@pytest.fixture
def overfill_next_launch(monkeypatch):
    """A function that makes the next inserting launch of any VoxelMap see a fill limit past its table's
    slots, so that its points plan to add in one pass and stop part way once every slot is taken, as a
    GPU's threads can when others take the room they saw. It returns what each relaunched item had added
    before it stopped (the flags its relaunch is handed, minus 1) and the maps of the launches after it."""
    import warp as wp

    from evsemmap_warp.core.voxel_map import VoxelMap

    def overfill():
        real_table, real_copy = VoxelMap.table, wp.copy
        resumed_after, launches = [], []

        def table_with_room_it_does_not_have(self):
            table = real_table(self)
            if not launches:
                table.max_count = 4 * self.capacity
            launches.append(self)
            return table

        def copy_seen(dest, src, *args, **kwargs):
            if any(m._failure_flags is not None and dest.ptr == m._failure_flags.ptr for m in launches):
                resumed_after.extend(src.numpy() - 1)
            return real_copy(dest, src, *args, **kwargs)

        monkeypatch.setattr(VoxelMap, "table", table_with_room_it_does_not_have)
        monkeypatch.setattr(wp, "copy", copy_seen)
        return resumed_after, launches

    return overfill


def stop_reading_partials_at(monkeypatch, chunk: int):
    """Make the batch fold stop (as on Ctrl-C) when it reads a partial of ``chunk``: a run killed halfway through
    folding. Returns the real reader, to put back before the rerun."""
    from evsemmap_warp.core import map_store

    original = map_store.read_partial

    def stop_at_chunk(path, columns, tile_voxels, identity, number):
        if number == chunk:
            raise KeyboardInterrupt
        return original(path, columns, tile_voxels, identity, number)

    monkeypatch.setattr(map_store, "read_partial", stop_at_chunk)
    return original
