"""The PCD reader on ascii and binary files, the toy files' quirk, and broken files."""

import numpy as np
import pytest

from evsemmap_warp.data.pcd import ExtraColumnsWarning, PcdError, read_pcd

from conftest import TOY_DIR

HEADER = """# .PCD v0.7
VERSION 0.7
FIELDS x y z label
SIZE 4 4 4 4
TYPE F F F U
COUNT 1 1 1 1
WIDTH {n}
HEIGHT 1
VIEWPOINT 1.5 -2 0.25 1 0 0 0
POINTS {n}
DATA {kind}
"""


def _write(tmp_path, text: bytes, name="c.pcd"):
    path = tmp_path / name
    path.write_bytes(text)
    return path


def test_ascii_and_binary_give_the_same_cloud(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    labels = rng.integers(0, 2**31, 50).astype(np.uint32)
    rows = "".join(f"{x!r} {y!r} {z!r} {lab}\n" for (x, y, z), lab in zip(xyz.tolist(), labels.tolist()))
    a = read_pcd(_write(tmp_path, (HEADER.format(n=50, kind="ascii") + rows).encode(), "a.pcd"))
    rec = np.zeros(50, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["label"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], labels
    b = read_pcd(_write(tmp_path, HEADER.format(n=50, kind="binary").encode() + rec.tobytes(), "b.pcd"))
    for cloud in (a, b):
        np.testing.assert_array_equal(cloud.points, xyz)
        np.testing.assert_array_equal(cloud.fields["label"], labels)
        np.testing.assert_array_equal(cloud.sensor_origin, [1.5, -2, 0.25])
        assert cloud.fields["x"].dtype == np.float32 and cloud.fields["label"].dtype == np.uint32


def test_toy_file_extra_column_is_ignored_with_a_warning():
    with pytest.warns(ExtraColumnsWarning, match="5 values but the header declares 4"):
        cloud = read_pcd(TOY_DIR / "sim_unstructured_annotated_1.pcd")
    assert len(cloud) == 3394
    np.testing.assert_allclose(cloud.points[0], [1.3917038, 1.4300275, 0.19733357], rtol=1e-7)
    assert set(np.unique(cloud.fields["label"])) <= {1, 2, 3}
    np.testing.assert_allclose(cloud.sensor_origin, [0.999984, 1.00002, 0.0997671])


@pytest.mark.parametrize(
    "text, message",
    [
        (HEADER.format(n=3, kind="ascii") + "1 2 3 0\n1 2 3 0\n", "declares 3 points, file has 2 data rows"),
        (HEADER.format(n=2, kind="ascii") + "1 2 3\n1 2 3 0\n", "fewer than the 4 declared values"),
        (HEADER.format(n=1, kind="ascii") + "1 2 x 0\n", "non-numeric value"),
        (HEADER.format(n=1, kind="binary_compressed"), "binary_compressed"),
        (HEADER.format(n=1, kind="ascii").replace("TYPE F F F U", "TYPE F F F X"), "unsupported TYPE X"),
        (HEADER.format(n=1, kind="ascii").replace("FIELDS x y z label", "FIELDS a y z label") + "1 2 3 0\n", "no field 'x'"),
        (HEADER.format(n=1, kind="ascii").replace("SIZE 4 4 4 4", "SIZE 4 4 4"), "different numbers of entries"),
        ("VERSION 0.7\nFIELDS x y z\n", "header ends before its DATA line"),
        (HEADER.format(n=1, kind="ascii").replace("VIEWPOINT 1.5 -2 0.25 1 0 0 0", "VIEWPOINT 1 2"), "VIEWPOINT needs 7 numbers"),
    ],
)
def test_broken_files_get_errors_that_name_the_problem(tmp_path, text, message):
    path = _write(tmp_path, text.encode())
    with pytest.raises(PcdError, match=message) as err:
        read_pcd(path)
    assert str(path) in str(err.value)


def test_truncated_binary_and_missing_file(tmp_path):
    path = _write(tmp_path, HEADER.format(n=10, kind="binary").encode() + b"\0" * 100)
    with pytest.raises(PcdError, match="truncated binary data: 100 bytes for 10 points"):
        read_pcd(path)
    with pytest.raises(PcdError, match="cannot read"):
        read_pcd(tmp_path / "nope.pcd")
