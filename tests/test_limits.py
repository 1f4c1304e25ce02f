"""The guards of issue 46: a memory budget on the voxel table, one definition of every limit shared by
the writers, the readers and the flags, and a timeout on joining Ray. Each case ran away (memory), wrote
what its reader refused, or hung once."""

import time
import traceback
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import run_cli

from evsemmap_warp import limits
from evsemmap_warp.apps import batch
from evsemmap_warp.apps.batch import BatchOptions, run_batch
from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.core import tile_codec, voxel_map
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.limits import MemoryBudgetError

REPO = Path(__file__).resolve().parents[1]
TOY = REPO / "configs/datasets/sbki_toy.yaml"




def _toy_without_range_filter(tmp_path) -> Path:
    config = yaml.safe_load(TOY.read_text())
    config["mapping"]["sbki"]["max_range_m"] = None
    config["dataset"]["paths"] = [str(REPO / "tests/data/sbki_toy")]
    path = tmp_path / "toy.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def _far_origin_scan(mapper: Mapper) -> None:
    """Issue 46 item 1, scaled down: 200 points 500 m from their sensor origin, no range filter; S-BKI's free
    space then fills a block of voxels every half metre of every ray (the issue's 5e4 m grew to 2^30 slots)."""
    rng = np.random.default_rng(0)
    mapper.integrate(rng.uniform(-5, 5, (200, 3)), rng.integers(0, 4, 200), payload_type="label", sensor_origin=np.array([500.0, 0, 0]))


def test_a_table_past_the_available_memory_is_refused_in_one_line(tmp_path, monkeypatch):
    run = load_config([str(_toy_without_range_filter(tmp_path))], method="s-bki")
    monkeypatch.setattr(voxel_map, "available_memory", lambda: 256 * 2**20)  # the default budget: what the machine has left
    mapper = Mapper(run.mapping, num_classes=4, workers=1)
    with pytest.raises(MemoryBudgetError, match=r"voxel table would need [0-9.]+ [GM]B \(.* slots.*over the memory budget of 2[56][0-9] MB, the memory available on cpu"):
        _far_origin_scan(mapper)


def test_max_memory_bounds_the_table_and_a_map_within_it_is_the_same(tmp_path):
    run = load_config([str(_toy_without_range_filter(tmp_path))], method="s-bki")
    with pytest.raises(MemoryBudgetError, match=r"over the memory budget of 64 MB, max_memory"):
        _far_origin_scan(Mapper(run.mapping, num_classes=4, workers=2, max_memory=64 * 2**20))
    rng = np.random.default_rng(1)
    points, labels = rng.uniform(-5, 5, (300, 3)), rng.integers(0, 4, 300)
    maps = [Mapper(run.mapping, num_classes=4, workers=1, max_memory=budget) for budget in (None, 64 * 2**20)]
    for mapper in maps:
        mapper.integrate(points, labels, payload_type="label", sensor_origin=np.zeros(3))
    assert maps[0].voxel_count == maps[1].voxel_count > 0
    with pytest.raises(ValueError, match="max_memory 1000 bytes is below 1 MiB"):
        Mapper(run.mapping, num_classes=4, max_memory=1000)


def test_sbki_asks_the_budget_before_it_lists_the_blocks_it_will_fill(tmp_path):
    """The S-BKI preparation lists every block's neighbours (arrays several times the blocks' size, 2.2 GB in
    the issue's case) before the launch grows the table: the budget is asked for the blocks' voxels first, so
    the refusal comes from the preparation (check_room), not from the launch's growth after those arrays."""
    run = load_config([str(_toy_without_range_filter(tmp_path))], method="s-bki")
    with pytest.raises(MemoryBudgetError) as refused:
        _far_origin_scan(Mapper(run.mapping, num_classes=4, workers=1, max_memory=64 * 2**20))
    steps = [frame.name for frame in traceback.extract_tb(refused.value.__traceback__)]
    assert "check_room" in steps and "gather_tables" in steps and "grow" not in steps, steps


def test_map_max_memory_is_one_line_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "m.npz"
    line = run_cli(capsys, "map", TOY, "--method", "s-bki", "--out", out, "--quiet", "--max-memory", "1M")
    assert "over the memory budget of 1 MB, max_memory (--max-memory)" in line
    assert not out.exists()
    assert "--max-memory '12Q' is not a size" in run_cli(capsys, "map", TOY, "--method", "s-bki", "--out", out, "--max-memory", "12Q")


def test_memory_sizes():
    assert limits.parse_memory_size("4G") == 4 * 2**30
    assert limits.parse_memory_size("1.5GiB") == 3 * 2**29
    assert limits.parse_memory_size("1048576") == 2**20
    with pytest.raises(ValueError, match="not a size"):
        limits.parse_memory_size("-4G")


@pytest.mark.parametrize("tile_voxels", [2**32, 10**18, limits.MAX_TILE_VOXELS + 1, 0])
def test_batch_refuses_a_tile_size_its_readers_refuse_before_writing_anything(tmp_path, capsys, tile_voxels):
    """Item 2 (2^32 and more wrapped the tile-local key: the run stopped on its own partial) and item 7
    (2^20 + 1 wrote stores that info and export refused)."""
    out = tmp_path / "store"
    line = run_cli(capsys, "batch", TOY, "--method", "s-csm", "--out", out, "--tile-voxels", tile_voxels)
    assert f"--tile-voxels {tile_voxels} must lie in 1..{limits.MAX_TILE_VOXELS}" in line
    with pytest.raises(ValueError, match=f"--tile-voxels {tile_voxels} must lie in 1..{limits.MAX_TILE_VOXELS}"):
        run_batch([str(TOY)], BatchOptions(method="s-csm", out=out, executor="inline", tile_voxels=tile_voxels, progress=False))
    assert not out.exists()


def test_merge_refuses_a_tile_size_its_readers_refuse(tmp_path, capsys):
    line = run_cli(capsys, "merge", tmp_path / "a.npz", tmp_path / "b.npz", "--out", tmp_path / "S", "--tile-voxels", 1048577)
    assert "--tile-voxels 1048577 must lie in 1..1048576" in line
    with pytest.raises(ValueError, match="--tile-voxels 1048577 must lie in"):
        batch.write_store_from_mapper(None, tmp_path / "S", 1048577, [])
    assert not (tmp_path / "S").exists()


@pytest.mark.parametrize("tile_voxels", [1, 256, limits.MAX_TILE_VOXELS, limits.MAX_TILE_VOXELS + 1, 2**32])
def test_the_codec_writes_exactly_the_tile_sizes_it_reads(tile_voxels):
    """One limit for writer and reader: a tile the codec writes it reads back, voxel for voxel, in key
    order, even at the far corner of the largest tile; a size it would not read it does not write."""
    corner = np.array([[0, 0, 0], [0, 0, tile_voxels - 1], [tile_voxels - 1, tile_voxels - 1, tile_voxels - 1]], np.int64)[-min(3, tile_voxels):]
    index = np.unique(corner, axis=0) + np.array([-1, 2, 0]) * tile_voxels
    rows = np.ones((len(index), 7))
    try:
        data = tile_codec.encode_voxels(index, rows, (-1, 2, 0), tile_voxels, {})
    except ValueError as exc:
        assert tile_voxels > limits.MAX_TILE_VOXELS and f"tile_voxels {tile_voxels} must lie in" in str(exc)
        return
    assert tile_voxels <= limits.MAX_TILE_VOXELS
    _, read, _ = tile_codec.decode_voxels(data, "tile")
    np.testing.assert_array_equal(read, index)


def test_batch_s_timeout_flags_default_to_the_run_s_limits(monkeypatch, capsys):
    """The flags' defaults and help are limits' constants, which the executors and BatchOptions take too: one place."""
    from evsemmap_warp.apps.cli import build_parser

    monkeypatch.setattr(limits, "CHUNK_TIMEOUT_S", 7.0)
    monkeypatch.setattr(limits, "RAY_CONNECT_TIMEOUT_S", 3.0)
    monkeypatch.setenv("COLUMNS", "1000")  # each flag's help on one line
    parser = build_parser()
    args = parser.parse_args(["batch", "drive", "--method", "ebs", "--out", "store"])
    assert (args.chunk_timeout_s, args.ray_connect_timeout_s) == (7.0, 3.0)
    with pytest.raises(SystemExit):
        parser.parse_args(["batch", "--help"])
    shown = capsys.readouterr().out
    assert "(default 7;" in shown and "refused (default 3)" in shown


def test_an_unreachable_ray_address_is_refused_within_its_timeout(tmp_path, capsys):
    """Item 3: ray.init retried "Failed to connect to GCS" at 127.0.0.1:9 for more than 10 minutes. No Ray
    instance is started here: the address is refused before Ray is asked."""
    started = time.monotonic()
    line = run_cli(capsys, "batch", TOY, "--method", "s-csm", "--out", tmp_path / "store", "--executor", "ray",
                      "--ray-address", "127.0.0.1:9", "--ray-connect-timeout-s", "5")
    assert time.monotonic() - started < 60
    assert "--ray-address 127.0.0.1:9: could not join the Ray instance (nothing accepted a connection at 127.0.0.1:9 within 5 s" in line
    assert not (tmp_path / "store").exists()
    with pytest.raises(ConfigError, match="the port 'x' is not a number"):
        batch.check_ray_address("10.0.0.9:x", 1.0)
