"""Map files in the layout evsemmap_warp wrote before format version 3 (one npz holding every array,
the read-out included, map_file.write_npz): the old writer, for the tests that old files still load
and are still validated."""

import json

import numpy as np

from evsemmap_warp.core.map_file import file_arrays, write_npz


def v2_arrays(mapper) -> dict:
    """The members of ``mapper``'s version-2 map file."""
    arrays = file_arrays(mapper.contents_of(*mapper.voxels()))
    meta = json.loads(str(arrays["meta"])) | {"format_version": 2}
    return arrays | {"meta": np.array(json.dumps(meta)), "format_version": np.int64(2)}


def write_v2_map(path, mapper):
    """``mapper`` written as a version-2 map file at ``path``; returns it."""
    with open(path, "wb") as f:
        write_npz(f, **v2_arrays(mapper))
    return path
