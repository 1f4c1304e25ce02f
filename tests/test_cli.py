"""The command line, run in-process the way a user types it."""

import json
from pathlib import Path

import numpy as np
import pytest

from evsemmap_warp.apps.cli import main
from evsemmap_warp.core.mapper import read_map_arrays

from conftest import REPO


def test_map_info_and_dump_config(tmp_path, capsys):
    out = tmp_path / "toy.npz"
    assert main(["map", str(REPO / "configs/datasets/sbki_toy.yaml"), "--method", "s-csm", "--out", str(out), "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    # the C++ has 6,988 OCCUPIED: one training point sums in another order (docs/compatibility.md §1.5)
    assert report["voxels"] == 64130 and report["states"]["OCCUPIED"] == 6987 and report["scans"] == 12
    arrays, meta = read_map_arrays(out)
    assert meta["classes"] == ["free", "ground", "wall", "obstacle"] and meta["mapping"]["compat"] == "sbki"
    assert (np.bincount(arrays["state"], minlength=3) == [41329, 15814, 6987]).all()
    assert main(["info", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["voxels"] == 64130 and info["format_version"] == 3
    half = info["resolution_m"] / 2  # the box the voxels fill: their faces, in metres of the map's frame
    assert info["bounds_m"] == [(arrays["centers"].min(axis=0) - half).tolist(), (arrays["centers"].max(axis=0) + half).tolist()]
    assert main(["dump-config", str(REPO / "configs/presets/rellis3d.yaml"), "--method", "ebs"]) == 0
    shown = capsys.readouterr().out
    assert "gamma: 10.0" in shown and "class_gains: false" in shown  # every key, also those maps record only when set


def test_info_counts_voxels_above_and_below_the_evidence_threshold(tmp_path, capsys):
    from test_viewer import make_map  # a map with kernel tails beside its surfaces

    make_map(tmp_path / "a.npz")
    make_map(tmp_path / "b.npz", seed=1, offset=(0.3, 0, 0))
    arrays, _ = read_map_arrays(tmp_path / "a.npz")
    above = arrays["evidence"].sum(axis=1) >= 0.2  # the layers' default min_evidence
    assert main(["info", str(tmp_path / "a.npz")]) == 0
    counts = json.loads(capsys.readouterr().out)["evidence_threshold"]
    assert counts["min_evidence"] == 0.2 and counts["known"] == above.sum() and counts["below"] == (~above).sum() > 100
    assert counts["below_by_state"]["OCCUPIED"] == (~above & (arrays["state"] == 2)).sum() > 100
    assert sum(counts["known_by_state"].values()) == counts["known"]
    costs = tmp_path / "costs.yaml"
    costs.write_text("layers: {min_evidence: 0.0}\n")
    assert main(["info", str(tmp_path / "a.npz"), "--costs", str(costs)]) == 0
    assert json.loads(capsys.readouterr().out)["evidence_threshold"]["below"] == 0
    # a store: its tiles' counts add up to the maps' merged
    assert main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "m.npz")]) == 0
    assert main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "store"), "--tile-voxels", "16"]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "m.npz")]) == 0
    merged = json.loads(capsys.readouterr().out)["evidence_threshold"]
    assert main(["info", str(tmp_path / "store")]) == 0
    assert json.loads(capsys.readouterr().out)["evidence_threshold"] == merged
    costs.write_text("layers: {min_evidence: -1}\n")
    assert main(["info", str(tmp_path / "a.npz"), "--costs", str(costs)]) == 2
    assert "min_evidence" in capsys.readouterr().err


def test_errors_exit_2_with_a_message(tmp_path, capsys):
    assert main(["map", str(REPO / "configs/presets/rellis3d.yaml"), "--method", "ebs", "--out", str(tmp_path / "m.npz")]) == 2
    assert "has a 'dataset' section" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "missing.npz")]) == 2
    assert "no such map file" in capsys.readouterr().err
    assert main(["train-seg", "--dataset", "rugd", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r")]) == 2
    assert "nowhere" in capsys.readouterr().err
    assert main(["infer", str(tmp_path / "missing.pt"), str(tmp_path / "no_images"), "--out", str(tmp_path / "o")]) == 2
    assert "missing.pt" in capsys.readouterr().err


@pytest.mark.filterwarnings("default::evsemmap_warp.data.pcd.ExtraColumnsWarning")
def test_a_warning_is_one_line_without_a_source_line(tmp_path, capsys):
    # The S-BKI toy scans carry an undeclared column: the command says so once, in one line.
    assert main(["map", str(REPO / "configs/datasets/sbki_toy.yaml"), "--method", "s-csm", "--out", str(tmp_path / "m.npz"),
                 "--quiet"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "column" in line or ".py:" in line]
    assert len(lines) == 1 and lines[0].startswith("evsemmap: warning: ") and "more columns" in lines[0], lines


@pytest.mark.parametrize("after_s", [0.15, 0.35, 2.0])
def test_ctrl_c_at_any_moment_is_one_line_and_exit_130(tmp_path, after_s):
    # while the command line's imports load (Warp, torch) as much as while it works (the default world takes ~30 s): no traceback
    import shutil
    import signal
    import subprocess
    import sys
    import time

    command = shutil.which("evsemmap", path=str(Path(sys.executable).parent))
    process = subprocess.Popen([command, "synth", "--world", "default", "--out", str(tmp_path / "seq"), "--quiet"],
                               stderr=subprocess.PIPE, text=True)
    time.sleep(after_s)
    # Warp's native start-up (the CUDA driver probe, a few ms) can swallow a SIGINT that lands inside it: sent again
    for _ in range(10):
        process.send_signal(signal.SIGINT)
        try:
            _, err = process.communicate(timeout=3)
            break
        except subprocess.TimeoutExpired:
            continue
    assert process.returncode == 130 and err.strip().splitlines()[-1:] == ["evsemmap: interrupted"] and "Traceback" not in err, err
