"""A/B of maps: the bench workload (../shared/data/bench/rellis_like_30scans.npz) mapped by this checkout
and by another one (a ``git worktree`` of the reference commit), compared byte for byte.

Each checkout maps in its own process: every method with the RELLIS-3D preset, at each worker count,
then every array of ``Mapper.voxels()`` (indices, evidence, weight sums, hits, touched) is compared.
Prints one line per (method, workers), writes docs/bench/ab_maps-<UTC>.json (both commits, every map's
voxel count and whether its bytes are the same, the fields that differ) and exits 1 when any map differs.

    git worktree add /tmp/main_ref HEAD
    python tools/ab_maps.py /tmp/main_ref [--methods ebs s-csm s-bki] [--workers 1 2] [--scans 30]

``--methods`` takes method names (the RELLIS-3D preset), ``release:ebs`` / ``release:dempster`` (the release
mode), ``sbki:F`` (the sbki mode with the C++ S-BKI bench parameters at free_resolution F) and ``sbki-csm:F`` (its
S-CSM).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
from bench_record import RECORDS, write_record  # noqa: E402

FIELDS = ("index", "evidence", "weight_sum", "weighted_uncertainty_sum", "hits", "touched")

# Run in a child with the checkout to test first on the path (the editable install's finder removed, so
# that ``evsemmap_warp`` and its kernels come from that checkout): maps every (method, workers).
CHILD = r"""
import sys, json, importlib.util
from pathlib import Path
root = Path(sys.argv[1])
sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in type(f).__module__.lower() + repr(f).lower()]
sys.path.insert(0, str(root))
spec = importlib.util.spec_from_file_location("evsemmap_warp", root / "evsemmap_warp" / "__init__.py",
                                              submodule_search_locations=[str(root / "evsemmap_warp")])
package = importlib.util.module_from_spec(spec)
sys.modules["evsemmap_warp"] = package
for name, folder in (("kernels", "kernels"), ("configs", "configs")):
    sub = importlib.util.spec_from_file_location(f"evsemmap_warp.{name}", root / folder / "__init__.py",
                                                 submodule_search_locations=[str(root / folder)])
    if sub is not None and (root / folder / "__init__.py").exists():
        module = importlib.util.module_from_spec(sub)
        sys.modules[f"evsemmap_warp.{name}"] = module
        sub.loader.exec_module(module)
spec.loader.exec_module(package)
import numpy as np
from evsemmap_warp.config import load_config
from evsemmap_warp.core.mapper import Mapper
import evsemmap_warp.kernels.scatter
for module in ("evsemmap_warp.core.mapper", "evsemmap_warp.kernels.scatter"):
    assert Path(sys.modules[module].__file__).resolve().is_relative_to(root.resolve()), f"{module}: imported from the wrong checkout"
work = np.load(sys.argv[2])
runs = json.loads(sys.argv[3])
out = {}
n = int(work["count"])
def config_of(method):
    # "release:M": the release preset (named evsemmap-release.yaml in older checkouts); "sbki:F": the sbki
    # mode with the C++ S-BKI bench parameters at free_resolution F; else the RELLIS-3D preset
    import dataclasses
    kind, _, rest = method.partition(":")
    if kind == "release":
        preset = next(p for p in (root / "configs/presets/release.yaml", root / "configs/presets/evsemmap-release.yaml") if p.exists())
        return load_config([preset], method=rest).mapping
    if kind in ("sbki", "sbki-csm"):
        base = load_config([root / "configs/presets/rellis3d.yaml"], method="s-csm" if kind == "sbki-csm" else "s-bki").mapping
        sbki = dict(block_depth=2, ds_resolution_m=0.1, free_resolution_m=float(rest))
        common = dict(compat=type(base.compat)("sbki"), media=type(base.media)("onehot"), adaptive_length=False,
                      uncertainty_threshold=False, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001)
        if hasattr(base, "sbki"):  # a checkout with the mode sections; older ones are flat
            return base.replace(sbki=sbki, **common)
        return dataclasses.replace(base, **common, **sbki)
    return load_config([root / "configs/presets/rellis3d.yaml"], method=method).mapping
for method, workers in runs:
    config = config_of(method)
    mapper = Mapper(config, int(work["num_classes"]), workers=workers)
    for i in range(n):
        mapper.integrate(work[f"points{i}"], work[f"payload{i}"], payload_type="alpha", sensor_origin=work[f"origin{i}"])
    arrays = mapper.voxels()[0]  # (arrays, summary); older checkouts return a plain tuple
    for field in %(fields)r:
        out[f"{method}@{workers}:{field}"] = np.ascontiguousarray(getattr(arrays, field))
np.savez(sys.argv[4], **out)
""" % {"fields": FIELDS}


def workload(scans: int, path: Path) -> None:
    sys.path.insert(0, str(REPO / "tools"))
    from bench_integrate import load_scans

    dataset, loaded = load_scans()
    loaded = loaded[:scans]
    arrays = {"count": len(loaded), "num_classes": dataset.num_classes}
    for i, scan in enumerate(loaded):
        arrays[f"points{i}"], arrays[f"payload{i}"], arrays[f"origin{i}"] = scan.points, scan.payload, scan.sensor_origin
    np.savez(path, **arrays)


def _commit(root: Path) -> str:
    return subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True).stdout.strip()


def maps_of(root: Path, work: Path, runs: list, out: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, str(root), str(work), json.dumps(runs), str(out)], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"mapping with {root} failed:\n{done.stderr[-3000:]}")
    with np.load(out) as data:
        return {key: data[key] for key in data.files}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reference", type=Path, help="the other checkout (e.g. a git worktree of the reference commit)")
    parser.add_argument("--methods", nargs="+", default=["ebs", "s-csm", "s-bki"])
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--scans", type=int, default=30)
    parser.add_argument("--record-dir", type=Path, default=RECORDS)
    args = parser.parse_args()
    started = time.time()
    runs = [(method, workers) for method in args.methods for workers in args.workers]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) / "work.npz"
        workload(args.scans, work)
        ours = maps_of(REPO, work, runs, Path(tmp) / "ours.npz")
        theirs = maps_of(args.reference.resolve(), work, runs, Path(tmp) / "theirs.npz")
    maps = []
    for method, workers in runs:
        keys = [f"{method}@{workers}:{field}" for field in FIELDS]
        same = [ours[k].dtype == theirs[k].dtype and ours[k].shape == theirs[k].shape and ours[k].tobytes() == theirs[k].tobytes() for k in keys]
        differing = [f for f, s in zip(FIELDS, same) if not s]
        maps.append({"method": method, "workers": workers, "voxels": len(ours[keys[0]]), "reference_voxels": len(theirs[keys[0]]),
                     "identical": not differing, "differing_fields": differing})
        print(f"{method} @ {workers} worker(s): {maps[-1]['voxels']:,} voxels, "
              + ("identical bytes" if not differing else "DIFFERENT: " + ", ".join(differing)))
    results = {"reference_commit": _commit(args.reference.resolve()), "scans": args.scans, "fields": list(FIELDS), "maps": maps}
    print(write_record("ab_maps", results, started=started, folder=args.record_dir))
    return 0 if all(m["identical"] for m in maps) else 1


if __name__ == "__main__":
    sys.exit(main())
