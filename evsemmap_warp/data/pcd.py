"""A small PCD (v0.7) reader: ascii and binary data, VIEWPOINT as the sensor origin.

Written by hand on purpose: open3d costs 627 MB and its legacy reader drops the ``label`` field, and binary
data is read without a Python loop over points. ``binary_compressed`` (LZF) is refused with a clear error.
Extra, undeclared columns in ascii files (the S-BKI toy scans carry a trailing ``-1``) are ignored with a
warning instead of corrupting the data, as PCL <= 1.11 did.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_TYPES = {("F", 4): np.float32, ("F", 8): np.float64, ("U", 1): np.uint8, ("U", 2): np.uint16,
          ("U", 4): np.uint32, ("U", 8): np.uint64, ("I", 1): np.int8, ("I", 2): np.int16,
          ("I", 4): np.int32, ("I", 8): np.int64}


class ExtraColumnsWarning(UserWarning):
    """Data rows carry more values than the header declares; the extra ones were ignored."""


class PcdError(ValueError):
    """The file is not a readable PCD; the message names the file and the problem."""


@dataclass
class PointCloud:
    """A PCD file's content: every field by name ([N], or [N, COUNT] for fields of several values), the
    VIEWPOINT (tx ty tz qw qx qy qz) and the path."""

    fields: dict[str, np.ndarray]  # name -> [N] or [N, COUNT] array
    viewpoint: np.ndarray  # [7]: tx ty tz qw qx qy qz
    path: Path

    @property
    def points(self) -> np.ndarray:
        """[N, 3] x, y, z in the file's dtype (m, the file's frame)."""
        return np.stack([self.fields["x"], self.fields["y"], self.fields["z"]], axis=1)

    @property
    def sensor_origin(self) -> np.ndarray:
        """[3] the VIEWPOINT's translation: where the sensor was (m, the file's frame)."""
        return self.viewpoint[:3].copy()

    def __len__(self) -> int:
        return len(self.fields["x"]) if "x" in self.fields else 0


def read_pcd(path) -> PointCloud:
    """Read a PCD v0.7 file (ascii or binary). Raises PcdError naming the file when the header is malformed,
    a type is unsupported, the data is truncated or disagrees with the header, or the data is
    ``binary_compressed``; warns (ExtraColumnsWarning) when ascii rows carry undeclared columns."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise PcdError(f"{path}: cannot read ({exc.strerror})") from None
    header, offset = _parse_header(raw, path)
    names, sizes, types, counts = header["FIELDS"], header["SIZE"], header["TYPE"], header["COUNT"]
    n = header["POINTS"]
    dtypes = []
    for name, size, typ in zip(names, sizes, types):
        key = (typ, size)
        if key not in _TYPES:
            raise PcdError(f"{path}: field {name!r} has unsupported TYPE {typ} SIZE {size}")
        dtypes.append(_TYPES[key])
    data_kind = header["DATA"]
    if data_kind == "ascii":
        columns = _read_ascii(raw[offset:], n, sum(counts), path)
    elif data_kind == "binary":
        record = np.dtype([(f"f{i}", dt, (c,)) for i, (dt, c) in enumerate(zip(dtypes, counts))])
        need = record.itemsize * n
        if len(raw) - offset < need:
            raise PcdError(f"{path}: truncated binary data: {len(raw) - offset} bytes for {n} points of {record.itemsize} bytes")
        if len(raw) - offset > need:
            raise PcdError(f"{path}: {len(raw) - offset} bytes of binary data, but the header declares {n} points of "
                           f"{record.itemsize} bytes ({need} bytes): POINTS, SIZE or COUNT is wrong")
        rec = np.frombuffer(raw, dtype=record, count=n, offset=offset)
        columns = np.concatenate([rec[f"f{i}"].astype(np.float64).reshape(n, -1) for i in range(len(names))], axis=1) if n else np.zeros((0, sum(counts)))
    else:
        raise PcdError(f"{path}: DATA {data_kind!r} is not supported (ascii and binary are; binary_compressed needs an LZF decoder)")
    fields, col = {}, 0
    for name, dt, c in zip(names, dtypes, counts):
        block = columns[:, col:col + c]
        col += c
        fields[name] = (block[:, 0] if c == 1 else block).astype(dt)
    for axis in "xyz":
        if axis not in fields:
            raise PcdError(f"{path}: no field {axis!r} (FIELDS {' '.join(names)})")
    return PointCloud(fields, np.asarray(header["VIEWPOINT"], dtype=np.float64), path)


def _parse_header(raw: bytes, path: Path):
    header: dict = {"VIEWPOINT": [0, 0, 0, 1, 0, 0, 0]}
    offset = 0
    while True:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise PcdError(f"{path}: header ends before its DATA line (truncated or not a PCD file)")
        line = raw[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        key = key.upper()
        if key in ("FIELDS", "TYPE"):
            header[key] = values
        elif key in ("SIZE", "COUNT"):
            header[key] = _ints(values, key, path)
        elif key in ("WIDTH", "HEIGHT", "POINTS"):
            header[key] = _ints(values, key, path)[0] if values else None
        elif key == "VIEWPOINT":
            try:
                header[key] = [float(v) for v in values]
            except ValueError:
                raise PcdError(f"{path}: VIEWPOINT {' '.join(values)!r} is not 7 numbers") from None
            if len(header[key]) != 7:
                raise PcdError(f"{path}: VIEWPOINT needs 7 numbers (tx ty tz qw qx qy qz), got {len(header[key])}")
        elif key == "DATA":
            header[key] = values[0].lower() if values else ""
            break
        elif key == "VERSION":
            continue
        else:
            raise PcdError(f"{path}: unknown header line {line!r}")
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in header:
            raise PcdError(f"{path}: header has no {key} line")
    header.setdefault("COUNT", [1] * len(header["FIELDS"]))
    lengths = {len(header[k]) for k in ("FIELDS", "SIZE", "TYPE", "COUNT")}
    if len(lengths) != 1:
        raise PcdError(f"{path}: FIELDS, SIZE, TYPE and COUNT list different numbers of entries")
    for key in ("POINTS", "WIDTH", "HEIGHT"):
        if header.get(key) is not None and header[key] < 0:
            raise PcdError(f"{path}: {key} {header[key]} is negative")
    if any(c < 1 for c in header["COUNT"]) or any(s < 1 for s in header["SIZE"]):
        raise PcdError(f"{path}: SIZE and COUNT entries must be >= 1 (SIZE {header['SIZE']}, COUNT {header['COUNT']})")
    organised = header["WIDTH"] * (header.get("HEIGHT") or 1) if header.get("WIDTH") is not None else None
    if header.get("POINTS") is None:
        if organised is None:
            raise PcdError(f"{path}: header has neither POINTS nor WIDTH")
        header["POINTS"] = organised
    elif organised is not None and organised != header["POINTS"]:
        raise PcdError(f"{path}: header declares POINTS {header['POINTS']} but WIDTH x HEIGHT = {organised}")
    return header, offset


def _ints(values, key, path):
    try:
        return [int(v) for v in values]
    except ValueError:
        raise PcdError(f"{path}: {key} {' '.join(values)!r} is not a list of integers") from None


def _read_ascii(body: bytes, n: int, declared_columns: int, path: Path) -> np.ndarray:
    lines = [ln for ln in body.decode("ascii", errors="replace").splitlines() if ln.strip()]
    if len(lines) < n:
        raise PcdError(f"{path}: truncated: header declares {n} points, file has {len(lines)} data rows")
    if len(lines) > n:
        raise PcdError(f"{path}: header declares POINTS {n}, but the file has {len(lines)} data rows")
    widths = {len(ln.split()) for ln in lines}
    if min(widths, default=declared_columns) < declared_columns:
        raise PcdError(f"{path}: some data rows have fewer than the {declared_columns} declared values")
    if max(widths, default=declared_columns) > declared_columns:
        warnings.warn(
            f"{path}: data rows have {max(widths)} values but the header declares {declared_columns}; the extra columns are ignored",
            ExtraColumnsWarning,
        )
    try:
        return np.array([ln.split()[:declared_columns] for ln in lines], dtype=np.float64).reshape(n, declared_columns)
    except ValueError as exc:
        raise PcdError(f"{path}: non-numeric value in the data ({exc})") from None
