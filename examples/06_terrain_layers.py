"""Terrain layers of a synthetic drive: map it, turn the map into the 2.5-D layers a planner reads
(elevation, slope, step, surface class and its uncertainty, traversability cost, lethal mask), write
them as a GeoTIFF, an npz, PNG previews and a ROS bag, and read the GeoTIFF back (docs/terrain.md).

    python examples/06_terrain_layers.py [--world tiny] [--out terrain_example] [--device cpu]
"""

import argparse
from pathlib import Path

import numpy as np

from evsemmap_warp import Mapper, load_config, open_dataset
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence
from evsemmap_warp.terrain import compute_layers, write_layers

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--world", default="tiny")
parser.add_argument("--out", type=Path, default=Path("terrain_example"))
parser.add_argument("--device", default="cpu")
args = parser.parse_args()

generate_sequence(load_preset(args.world), args.out / "sequence", progress=False, camera=False)
run = load_config([str(args.out / "sequence")], method="ebs")
dataset = open_dataset(run.dataset)
mapper = Mapper.for_dataset(dataset, run.mapping, device=args.device)
mapper.integrate_many(dataset)

layers = compute_layers(mapper, device=args.device)   # cells of the map's voxel size, the map's world frame
cost, known = layers.bands["traversability_cost"], layers.bands["known"] > 0
by_class = {name: float(np.nanmedian(cost[layers.bands["surface_class"] == c])) for c, name in enumerate(layers.class_names)
            if (layers.bands["surface_class"] == c).any()}
print(f"{layers.grid.width} x {layers.grid.height} cells of {layers.grid.cell_m} m in {mapper.frame.describe()}: "
      f"{known.sum()} known, {int(layers.bands['lethal'].sum())} lethal")
print("median cost by surface class: " + ", ".join(f"{name} {value:.2f}" for name, value in by_class.items()))

summary = write_layers(mapper, args.out / "layers", device=args.device)   # what `evsemmap layers MAP --out DIR` writes
print("wrote " + ", ".join(summary["files"][:4]) + f", ... ({len(summary['files'])} files) to {args.out / 'layers'}")
try:
    import rasterio
except ImportError:
    print("rasterio is not installed (pip install 'evsemmap_warp[geo]'): the GeoTIFF was not read back")
else:
    with rasterio.open(args.out / "layers" / "layers.tif") as tif:
        elevation = tif.read(tif.descriptions.index("elevation") + 1)
        print(f"GeoTIFF: {tif.count} bands, frame {tif.tags()['FRAME']}, the same elevation: "
              f"{np.array_equal(elevation, layers.bands['elevation'], equal_nan=True)}")
print("OK")
