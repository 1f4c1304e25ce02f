"""Every example runs, with small sizes, as a user would run it."""

import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO


def _run(*args, cwd):
    done = subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_quickstart(tmp_path):
    out = _run(str(REPO / "examples/00_quickstart.py"), "--points", "4000", "--out", str(tmp_path / "q.npz"), cwd=tmp_path)
    accuracy = float(out.split("label accuracy there: ")[1].split("%")[0])
    assert accuracy > 90 and (tmp_path / "q.npz").exists()


def test_sbki_toy_conformance(tmp_path):
    out = _run(str(REPO / "examples/01_sbki_toy_conformance.py"), cwd=tmp_path)
    assert "s-csm: 64130 cells" in out and "s-bki: 215936 cells" in out


def test_view_map(tmp_path):
    from evsemmap_warp.apps.viewer import free_port

    out = _run(str(REPO / "examples/02_view_map.py"), "--no-serve", "--port", str(free_port()), "--out-dir", str(tmp_path), cwd=tmp_path)
    assert "toy_maps.html" in out and (tmp_path / "toy_s-bki.npz").exists() and (tmp_path / "toy_s-csm.npz").exists()


def test_synthetic_world(tmp_path):
    out = _run(str(REPO / "examples/03_synthetic_world.py"), "--out", str(tmp_path / "s"), cwd=tmp_path)
    agreement = float(out.split("labels agree on ")[1].split("%")[0])
    assert agreement > 90 and (tmp_path / "s" / "overlay.png").exists() and "OK" in out


def test_compare_methods(tmp_path):
    out = _run(str(REPO / "examples/04_compare_methods.py"), "--out", str(tmp_path / "c"), cwd=tmp_path)
    rows = {line.split("|")[1].strip(): float(line.split("|")[2]) for line in out.splitlines() if line.startswith("| ") and "method" not in line}
    assert set(rows) == {"s-csm", "s-bki", "convbki", "see-csom", "dempster", "ebs"}
    assert all(0 < miou <= 100 for miou in rows.values()) and (tmp_path / "c" / "ebs.npz").exists()


def test_robot_log(tmp_path):
    pytest.importorskip("rosbags")
    out = _run(str(REPO / "examples/05_robot_log.py"), "--format", "rosbag1", "--out", str(tmp_path / "l"), cwd=tmp_path)
    assert "the folder's map is the same: True" in out and "OK" in out and (tmp_path / "l" / "drive.bag").exists()


def test_terrain_layers(tmp_path):
    pytest.importorskip("rasterio")
    out = _run(str(REPO / "examples/06_terrain_layers.py"), "--out", str(tmp_path / "t"), cwd=tmp_path)
    assert "the same elevation: True" in out and "OK" in out and (tmp_path / "t" / "layers" / "layers.bag").exists()


def test_drive_playback(tmp_path):
    from evsemmap_warp.apps.viewer import free_port

    out = _run(str(REPO / "examples/07_drive_playback.py"), "--no-serve", "--port", str(free_port()), "--out", str(tmp_path / "p"),
               cwd=tmp_path)
    counts = [int(line.split(": ")[1].split(" voxels")[0].replace(",", "")) for line in out.splitlines() if line.startswith("after scan")]
    assert len(counts) == 6 and counts == sorted(counts) and counts[0] < counts[-1]  # the map as it grew, scan by scan
    assert "give the map file back" in out


def test_live_map(tmp_path):
    from evsemmap_warp.apps.viewer import free_port

    out = _run(str(REPO / "examples/08_live_map.py"), "--no-serve", "--port", str(free_port()), "--out", str(tmp_path / "l"), cwd=tmp_path)
    assert "the map shown is the map written: True" in out and int(out.split(" updates while mapping")[0].split()[-1]) >= 1


def test_store_overview(tmp_path):
    from evsemmap_warp.apps.viewer import free_port

    out = _run(str(REPO / "examples/09_store_overview.py"), "--no-serve", "--port", str(free_port()), "--out", str(tmp_path / "s"),
               cwd=tmp_path)
    first = out.split("first frame ready in ")[1]
    assert int(first.split(": ")[1].split(" of ")[0]) < int(first.split(" of ")[1].split(" tiles")[0])  # before the store was read
    assert "tile(s) in full" in out


def test_compare_maps(tmp_path):
    from evsemmap_warp.apps.viewer import free_port

    out = _run(str(REPO / "examples/10_compare_maps.py"), "--no-serve", "--port", str(free_port()), "--out", str(tmp_path / "c"), cwd=tmp_path)
    differ = int(out.split("labels differ in ")[1].split(";")[0].replace(",", ""))
    counts = {line.split(": ")[0].strip(): int(line.split(": ")[1].replace(",", "")) for line in out.splitlines()
              if line.startswith(("  first map", "  second map", "  neither", "  labels differ"))}
    assert len(counts) == 4 and sum(counts.values()) == differ > 0  # every differing voxel in one category
    assert counts["first map agrees with the truth"] > 0 and counts["second map agrees with the truth"] > 0
    assert "the counts checked against numpy: True" in out and "checked against numpy: True" in out.split("variance difference")[1]


def test_orientation_and_measuring(tmp_path):
    from evsemmap_warp.apps.viewer import free_port

    out = _run(str(REPO / "examples/11_orientation_and_measuring.py"), "--no-serve", "--port", str(free_port()), "--out", str(tmp_path / "m"),
               cwd=tmp_path)
    assert "lines every 10 m" in out and "x 0 m" in out and "y 0 m" in out
    meters, pixels = out.split("scale bar at the initial camera: ")[1].split(" px long")[0].split(" m drawn ")
    assert float(meters) in (1, 2, 5, 10, 20, 50) and 50 <= float(pixels) <= 120
    points = [np.array([float(v.split("=")[1]) for v in line.split(": ")[1].removesuffix(" m").split(", ")])
              for line in out.splitlines() if line.startswith("clicked point in")]
    assert len(points) == 2
    under_center = out.split("under the screen's center (a voxel of map, ")[1].split("\n")[0]
    center = np.array([float(v.split("=")[1]) for v in under_center.split("): ")[1].split(" m in ")[0].split(", ")])
    assert np.allclose(center, points[0], atol=0.01)  # the highest voxel's top, as the first click finds it
    distance = float(out.split("distance ")[1].split(" m")[0])
    height = float(out.split("height difference ")[1].split(" m")[0])
    assert abs(distance - np.linalg.norm(points[1] - points[0])) < 2e-3 and abs(height - (points[1][2] - points[0][2])) < 2e-3
    assert distance > 10 and "checked against numpy: True" in out


def test_examples_are_all_tested():
    names = sorted(p.name for p in (REPO / "examples").glob("*.py"))
    assert names == ["00_quickstart.py", "01_sbki_toy_conformance.py", "02_view_map.py", "03_synthetic_world.py", "04_compare_methods.py",
                     "05_robot_log.py", "06_terrain_layers.py", "07_drive_playback.py", "08_live_map.py", "09_store_overview.py",
                     "10_compare_maps.py", "11_orientation_and_measuring.py"], \
        "add a test for each new example"


def test_readme_python_snippet_makes_a_sensible_map(tmp_path, monkeypatch):
    """The README's Python block, run as written on a tiny synthetic sequence in place of the default one."""
    import re

    from evsemmap_warp.synthetic.preset import load_preset
    from evsemmap_warp.synthetic.writer import generate_sequence

    readme = (REPO / "README.md").read_text()
    snippet = re.search(r"```python\n(.*?)```", readme, re.S).group(1)
    assert "data/synth/00000" in snippet
    generate_sequence(load_preset("tiny"), tmp_path / "data/synth/00000", progress=False)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(snippet, "README.md", "exec"), namespace)
    mapper, result, scan = namespace["mapper"], namespace["result"], namespace["scan"]
    assert mapper.voxel_count > 1000 and (tmp_path / "synth_ebs.npz").exists()
    assert (result.label == scan.payload).mean() > 0.9  # the map gives the scan's own labels back
