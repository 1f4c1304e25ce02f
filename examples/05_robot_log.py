"""A drive recorded as a robot log becomes a semantic map: write the synthetic drive as a ROS 1 bag, a
ROS 2 bag or an MCAP file, check it, map it from its labelled clouds, and compare with the same drive
mapped from its folder. Needs the ros extra (pip install "evsemmap_warp[ros]").

    python examples/05_robot_log.py [--format mcap] [--out log_example]
"""

import argparse
from pathlib import Path

import numpy as np

from evsemmap_warp import Mapper, load_config, open_dataset
from evsemmap_warp.data.log_writer import LOG_FORMATS, write_log
from evsemmap_warp.data.logs import check_log
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--format", choices=LOG_FORMATS, default="mcap")
parser.add_argument("--out", type=Path, default=Path("log_example"))
args = parser.parse_args()

folder, log = args.out / "folder", args.out / {"rosbag1": "drive.bag", "rosbag2": "drive", "mcap": "drive.mcap"}[args.format]
generate_sequence(load_preset("tiny"), folder, progress=False)
print(write_log(folder, log, args.format))
run = load_config([str(log), "rellis3d-bag"])
print(check_log([log], run.dataset.bag).text())  # topics, rates, what is missing


def build_map(sources):
    run = load_config(sources, method="ebs")
    dataset = open_dataset(run.dataset)  # a bag dataset streams clouds, posed by the TF tree at their stamps
    mapper = Mapper.for_dataset(dataset, run.mapping)  # in the log's fixed frame, or the folder's poses' frame
    for scan in dataset:
        mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
    return mapper


from_log, from_folder = build_map([str(log), "rellis3d-bag"]), build_map([str(folder)])
(a, sa), (b, sb) = from_log.voxels(), from_folder.voxels()
same = np.array_equal(a.index, b.index) and np.array_equal(sa.label, sb.label)
print(f"{from_log.voxel_count} voxels from the {args.format} log; the folder's map is the same: {same} "
      f"(largest evidence difference {np.abs(a.evidence - b.evidence).max():.1e})")
