"""Every mapping method on the same projected data, scored against the 3D ground truth: the Python
API under `evsemmap experiment`. A stand-in "network" gives each pixel a Dirichlet from the 2D
ground truth, with a share of confidently wrong and of uncertain pixels, so no training is needed.

    python examples/04_compare_methods.py [--world tiny] [--out compare_example]
"""

import argparse
from pathlib import Path

import numpy as np

from evsemmap_warp import Mapper, available_methods, load_config, preset_path
from evsemmap_warp.classes import class_set, remap_ids
from evsemmap_warp.apps.evaluation import evaluate_map, markdown_table
from evsemmap_warp.geometry.projection import ProjectionConfig, label_map_for, project_frames
from evsemmap_warp.data.sequences import Rellis3DSequence
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--world", default="tiny")
parser.add_argument("--out", type=Path, default=Path("compare_example"))
args = parser.parse_args()

generate_sequence(load_preset(args.world), args.out / "sequence", progress=False)
seq = Rellis3DSequence(args.out / "sequence")
rng = np.random.default_rng(0)


def stand_in_alpha(frame):
    """[9, H/2, W/2] alpha: 20 evidence on the true class; 10 % of pixels confidently wrong, 20 % vague."""
    truth = remap_ids(seq.read_label_ids(frame), str(frame.label_image))[::2, ::2]
    predicted = np.where(rng.random(truth.shape) < 0.1, rng.integers(0, 9, truth.shape), truth)
    evidence = np.where(rng.random(truth.shape) < 0.2, 0.5, 20.0)
    alpha = np.ones((9, *truth.shape), np.float32)
    np.put_along_axis(alpha, predicted[None], 1 + evidence[None], axis=0)
    return alpha


# Poses as given: the map and the ground truth sit in the sequence's own (world) frame.
scans = list(project_frames(seq, seq.frames, stand_in_alpha, ProjectionConfig()))
truth = list(project_frames(seq, seq.frames, label_map_for(seq), ProjectionConfig()))
gt_points, gt_labels = np.concatenate([t.points for t in truth]), np.concatenate([t.values for t in truth])

rows = {}
for method in ["s-csm", "s-bki", "convbki", "see-csom", "dempster", "ebs"]:
    assert method in available_methods()
    mapper = Mapper(load_config([preset_path("offroad")], method=method).mapping, 9, class_names=class_set().names)
    for scan in scans:
        mapper.integrate(scan.points, scan.values, payload_type="alpha", sensor_origin=scan.sensor_origin)
    rows[method] = evaluate_map(mapper, gt_points, gt_labels).row()
    mapper.save(args.out / f"{method}.npz")
print(markdown_table(rows, ["mIoU", "Acc", "O.Acc", "BS"]))
print(f"maps: {args.out}/<method>.npz (evsemmap view {args.out}/ebs.npz)")
